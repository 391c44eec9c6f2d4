"""What the command line says and where: logging (text or JSON lines for journald),
verbosity, progress — all on stderr, so that stdout carries only a command's result
(``--json``: one JSON document and nothing else).

- :func:`setup_logging` — the root logger on stderr at a level from ``--log-level`` or
  ``-v``/``-q``; ``warnings`` go through logging (stderr); ``--log-json``: one JSON object
  per line (``ts``, ``level``, ``logger``, ``msg`` and the record's ``event`` fields).
- :func:`progress` — a tqdm bar on a terminal; elsewhere (a pipe, a CI log, journald) one
  line every ``period_s`` ("thesis: 12/40 seed (30 %), 1m20s"); nothing with ``--quiet``.
- :func:`heartbeat` — for work whose size is unknown (benchmarks): elapsed time, periodically.
"""
from __future__ import annotations

import json
import logging
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Iterator

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

_state = {"quiet": False, "stage": ""}


class JsonFormatter(logging.Formatter):
    """One JSON object per record (journald/ELK friendly); ``extra={"event": {...}}``
    fields are merged in."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {"ts": round(record.created, 3), "level": record.levelname, "logger": record.name,
                               "msg": record.getMessage()}
        event = getattr(record, "event", None)
        if isinstance(event, dict):
            doc.update(event)
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


def level_for(log_level: str | None, verbose: int = 0, quiet: bool = False, default: str = "WARNING") -> int:
    """The root level: ``--log-level`` wins; else ``default`` one step lower per ``-v``,
    ERROR with ``-q``."""
    if log_level:
        return getattr(logging, log_level.upper())
    if quiet:
        return logging.ERROR
    return max(logging.DEBUG, getattr(logging, default) - 10 * verbose)


class _StderrHandler(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is at each record (a test's capture, a
    redirected stream), not the stream that was current when it was installed."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(level: int, json_lines: bool = False, quiet: bool = False) -> None:
    """Configure the root logger on stderr (replacing handlers a previous call installed)."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "_adaptnav", False):
            root.removeHandler(h)
    handler = _StderrHandler()
    handler._adaptnav = True  # type: ignore[attr-defined]
    handler.setFormatter(JsonFormatter() if json_lines else logging.Formatter(TEXT_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)
    logging.captureWarnings(True)  # warnings.warn → logging → stderr
    _state["quiet"] = quiet


def quiet() -> bool:
    return bool(_state["quiet"])


def stage(text: str) -> None:
    """What a long command is doing now (e.g. "latency (3 of 8)"): :func:`heartbeat`'s lines
    say it instead of "running"; "" clears it."""
    _state["stage"] = str(text)


class LineProgress:
    """tqdm's ``update``/``close``/context API as one stderr line every ``period_s``."""

    def __init__(self, total: float | None, desc: str, unit: str, period_s: float = 10.0) -> None:
        self.total, self.desc, self.unit, self.period_s = total, desc, unit, period_s
        self.n = 0.0
        self.t0 = time.monotonic()
        self._next = self.t0 + period_s

    def _line(self) -> str:
        elapsed = time.monotonic() - self.t0
        done = f"{self.n:.0f}/{self.total:.0f} {self.unit}" if self.total else f"{self.n:.0f} {self.unit}"
        pct = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        return f"{self.desc}: {done}{pct}, {_hms(elapsed)} elapsed"

    def update(self, n: float = 1) -> None:
        self.n += n
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.period_s
            print(self._line(), file=sys.stderr, flush=True)

    def close(self) -> None:
        pass

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _hms(s: float) -> str:
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m{s % 60:02d}s" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def progress(total: float | None, desc: str, unit: str = "it", enabled: bool = True,
             period_s: float = 10.0, **tqdm_kwargs: Any) -> Any:
    """A progress object with ``update(n)``/``close()``: tqdm on a terminal (stderr), a
    periodic line otherwise, ``None`` when disabled or ``--quiet``."""
    if not enabled or quiet():
        return None
    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, **tqdm_kwargs)
    return LineProgress(total, desc, unit, period_s)


@contextmanager
def heartbeat(desc: str, period_s: float = 15.0) -> Iterator[None]:
    """While the block runs: "<desc>: running, 1m30s elapsed" on stderr every ``period_s``
    ("running" replaced by the :func:`stage` set inside the block; rewritten in place on a
    terminal); nothing with ``--quiet``."""
    if quiet():
        yield
        return
    stop = threading.Event()
    t0 = time.monotonic()
    tty = sys.stderr.isatty()

    def beat() -> None:
        while not stop.wait(1.0 if tty else period_s):
            line = f"{desc}: {_state['stage'] or 'running'}, {_hms(time.monotonic() - t0)} elapsed"
            print(("\r\033[K" + line) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)

    thread = threading.Thread(target=beat, name="adaptnav-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        _state["stage"] = ""
        if tty:
            print("\r\033[K", end="", file=sys.stderr, flush=True)
