"""A log's reading in a child process: decoding and conversion on the second core while this
process navigates.

Replaying a MAVLink log (``.tlog``, DataFlash ``.bin``, a BlueOS ``.mcap``) spends about half
its time reading: pymavlink's decoding of every frame, the conversion into samples, the
re-order buffer. That half needs nothing of the navigation, so a child process does it and
hands the samples over in chunks through a pipe; this process orders and batches them (the
two processes' shares of the work are then about even) and gets the same items in the same
order, so the replay's outputs are the same bytes.

What the replay reads of the source while it runs is mirrored sample by sample: the UNIX time of a
mission time (:meth:`TlogReplaySource.unix_of`: the clock's offset as the log's reader had
learnt it when it handed the sample out). What it reads at the end (counters, what is missing,
whether there is truth) comes with the last chunk. The child's log records are logged here, as the
reading's own are in-process. An exception of the reading is raised here; a child that dies
raises ``RuntimeError``.
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import sys
from pathlib import Path
from typing import Any, Iterator

# items per hand-over (a tlog's busy second is ~100 items: a few hand-overs a second of data)
CHUNK_ITEMS = 512
# "auto" reads in a child from this size on: a smaller log gains less than the child costs
# (starting it, handing the items over)
CHILD_MIN_BYTES = 4_000_000
READERS = ("auto", "process", "inline")


def wants_child(path: Path | None, reader: str) -> bool:
    """Whether ``reader`` (one of :data:`READERS`) reads the log at ``path`` in a child process:
    ``process`` always, ``inline`` never, ``auto`` for a log of :data:`CHILD_MIN_BYTES` or more
    on a machine with a second core."""
    if reader not in READERS:
        raise ValueError(f"reader must be one of {', '.join(READERS)}, got {reader!r}")
    if reader != "auto":
        return reader == "process"
    try:
        big = path is not None and os.path.getsize(path) >= CHILD_MIN_BYTES
    except OSError:
        return False
    return big and (os.cpu_count() or 1) >= 2


def _context() -> Any:
    """A fork of this process where there is fork: it has imported what the reader needs and
    the child starts at once (the calibrator's forkserver took ~1 s more: its preloading; a
    spawned child re-imports). The calibrator avoids plain fork for OpenCV's thread pool, which
    the reader never touches; what it does touch (logging, the import system) CPython
    re-initialises in a forked child."""
    if "fork" in mp.get_all_start_methods():
        return mp.get_context("fork")
    return mp.get_context("spawn")


class _Forward(logging.Handler):
    """The child's log records, kept for the next hand-over."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.name, record.levelno, record.getMessage()))


def _reader_main(path: str, calls: list, conn: Any, level: int, chunk_items: int, parent_end: Any = None) -> None:
    """The child: open the log as the parent did, make the parent's configuration calls, read.

    A forked child holds a copy of the parent's end of the pipe (``parent_end``) and the
    parent's signal handlers. Both go first: with that copy closed, a parent that lets go of
    the source (a replay stopped early) makes the next hand-over fail here (a broken pipe), and
    the child ends by itself; with SIGTERM at its default, the parent's ``terminate`` ends it
    whatever the parent had installed (``adaptnav record``'s handler only set an event: the
    child, blocked on a full pipe it could read itself, outlived a stopped replay for ever).
    Ctrl-C is left to the parent, as in the calibrator's child."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if parent_end is not None:
        parent_end.close()
    forward = _Forward()
    root = logging.getLogger()
    root.handlers[:] = [forward]
    root.setLevel(level)
    try:
        from adaptnav.service.runtime.sources import tlog_source

        src = tlog_source(Path(path))
        # what opening the log said (a damaged index, repaired formats): the parent opened the
        # same file with the same code and has said it already
        forward.records.clear()
        for name, args in calls:
            getattr(src, name)(*args)
        tlog = src.tlog
        items: list = []
        offsets: list = []  # (index in the chunk, UNIX offset from then on)
        last: Any = object()
        for item in tlog:  # its samples (the parent orders and batches them, as it would in-process)
            offset = tlog.converter.time.unix_offset_s
            if offset != last:
                offsets.append((len(items), offset))
                last = offset
            items.append(item)
            if len(items) >= chunk_items:
                conn.send(("items", items, offsets, forward.records))
                items, offsets, forward.records = [], [], []
        conn.send(("items", items, offsets, forward.records))
        forward.records = []
        conn.send(("end", tlog.counters, tlog.missing, tlog.has_truth))
    except BaseException as e:  # noqa: BLE001 — said to the parent, which raises it
        for error in (e, RuntimeError(f"{type(e).__name__}: {e}")):  # (the words of one that does not pickle)
            try:
                conn.send(("error", error, forward.records))
                break
            except OSError:  # the parent let go of the source (it stopped early): nobody to tell
                break
            except Exception:  # noqa: BLE001 — not picklable: its words next
                continue
    finally:
        conn.close()


def read_in_child(source: Any) -> Iterator[Any]:
    """The samples of ``source``'s log (a :class:`adaptnav.service.runtime.sources.TlogReplaySource`
    not yet read, its configuration calls recorded), read in a child process; see the module
    docstring."""
    ctx = _context()
    # a forked child flushes its copy of the standard streams when it ends: nothing pending there
    sys.stdout.flush()
    sys.stderr.flush()
    receive, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_reader_main, name="adaptnav-log-reader", daemon=True,
                       args=(str(source.tlog.path), list(source.calls), send,
                             logging.getLogger().getEffectiveLevel(), CHUNK_ITEMS,
                             receive if ctx.get_start_method() == "fork" else None))
    proc.start()
    send.close()  # (the child's end: EOF here when the child is gone)
    clock = source.tlog.converter.time
    tlog = source.tlog
    try:
        while True:
            try:
                message = receive.recv()
            except EOFError:
                proc.join(5.0)
                raise RuntimeError(f"the log reader process ended without finishing "
                                   f"{tlog.path.name} (exit code {proc.exitcode})") from None
            kind = message[0]
            if kind == "items":
                _, items, offsets, records = message
                _relog(records)
                changes = iter(offsets)
                at, offset = next(changes, (None, None))
                for i, item in enumerate(items):
                    if i == at:
                        clock.unix_offset_s = offset
                        at, offset = next(changes, (None, None))
                    yield item
            elif kind == "end":
                _, counters, missing, has_truth = message
                tlog.counters, tlog.missing, tlog.has_truth = counters, missing, has_truth
                return
            else:
                _, error, records = message
                _relog(records)
                raise error
    finally:
        receive.close()
        proc.join(2.0)
        if proc.is_alive():  # the replay stopped early and the child has not noticed yet
            proc.terminate()
            proc.join(5.0)
            if proc.is_alive():  # (no reader outlives its replay)
                proc.kill()
                proc.join()


def _relog(records: list[tuple[str, int, str]]) -> None:
    for name, level, text in records:
        logging.getLogger(name).log(level, "%s", text)
