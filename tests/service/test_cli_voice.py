"""The command line behaves like the tools robotics engineers know: ``--version``, ``-v``/``-q``,
unknown log levels refused, logs/progress on stderr (``--json``: stdout is the JSON and
nothing else), lifecycle events once each, JSON log lines on request; the daemon says why
it cannot start in one line (exit 2) and stops on Ctrl-C without a traceback from any of
its processes."""
from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from adaptnav.service.cli import main

pytestmark = pytest.mark.timeout(180)

ADAPTNAV = [sys.executable, "-m", "adaptnav"]


def _run(args, **kw):
    return subprocess.run(ADAPTNAV + args, capture_output=True, text=True, timeout=150, **kw)


def test_version_and_unknown_log_level(capsys):
    from adaptnav import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"adaptnav {__version__}"
    with pytest.raises(SystemExit) as e:
        main(["run", "--log-level", "verbose", "--print-config"])
    assert e.value.code == 2 and "unknown log level 'verbose'" in capsys.readouterr().err
    # accepted in any case, before or after the verb
    assert main(["--log-level", "debug", "run", "--print-config"]) == 0
    assert main(["run", "-q", "--print-config"]) == 0


def test_json_stdout_is_only_the_json_object(tmp_path):
    res = _run(["-v", "replay", "--scenario", "short", "--set", "duration_s=60", "--out", str(tmp_path / "r"),
                "--no-plots", "--json"])
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)  # the whole stdout is one JSON document
    assert doc["input"] == "scenario short" and doc["duration_s"] > 50
    assert "aligned" in res.stderr  # -v: the lifecycle events went to stderr


def test_line_progress_off_a_terminal(capsys):
    from adaptnav.service import console

    console.setup_logging(logging.WARNING)
    bar = console.progress(10, "thesis", "seed", period_s=0.0)
    assert isinstance(bar, console.LineProgress)  # pytest's stderr is not a terminal
    for _ in range(4):
        bar.update(1)
    bar.close()
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("thesis: 4/10 seed (40 %)") and len(err) == 4
    console.setup_logging(logging.WARNING, quiet=True)
    assert console.progress(10, "thesis") is None
    console.setup_logging(logging.WARNING)


def test_bench_arguments_it_cannot_run_with_are_one_line_and_exit_2(capsys):
    """A typo in ``--only`` or a bad ``--latency-s``: one line naming what is wrong (and the
    parts there are), exit 2, nothing measured — not a traceback."""
    assert main(["bench", "service", "--only", "replay,latncy"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["adaptnav bench service: --only: unknown parts ['latncy'] (known: replay, floor, latency, "
                   "mavlink_cpu, cold_call, cold_start, memory, live_work, memory_mavlink)"], err
    assert main(["bench", "service", "--only", "latency", "--latency-s", "nan"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["adaptnav bench service: --latency-s must be a positive number of seconds, got nan"], err
    # another target's option was ignored without a word
    assert main(["bench", "calibration", "--only", "replay"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["adaptnav bench calibration: --only is an option of `adaptnav bench service` only"], err
    # the soak's sampling period: 0 was taken for 30 s without a word
    assert main(["bench", "soak", "--sample-s", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["adaptnav bench soak: --sample-s must be within (0, the soak's 3600 s], got 0"], err


def test_replay_pace_that_is_no_speed_is_one_line_and_exit_2(capsys, tmp_path):
    """``--realtime -3`` (or 0, NaN): one line and exit 2 before anything is read — it was the
    clock's ValueError traceback."""
    for speed in ("-3", "0", "nan"):
        assert main(["replay", "--scenario", "short", "--realtime", speed, "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"adaptnav replay: --realtime SPEED must be a positive number, got {float(speed):g}"], err
    # the wrong model's k_V × (1 + E) must stay positive: -5 was MotionParams' traceback
    for e in ("-5", "-1", "nan"):
        assert main(["replay", "--scenario", "short", "--compare", "--motion-k-v-error", e,
                     "--out", str(tmp_path)]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [
            f"adaptnav replay: --motion-k-v-error E must be above -1 (k_V × (1 + E) > 0), got {float(e):g}"]


def test_record_duration_and_experiment_numbers_that_are_no_numbers_are_one_line_and_exit_2(capsys, tmp_path):
    """``record --duration nan`` recorded forever (NaN never reached); ``experiment thesis
    --sensor-noise nan`` ran with a NaN noise; the experiment's other refusals exited 1. Each is
    one line and exit 2 now, before anything connects or runs."""
    assert main(["record", "--out", str(tmp_path / "r.mcap"), "--duration", "nan"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "adaptnav record: --duration must be a positive number of seconds, got nan"]
    assert not (tmp_path / "r.mcap").exists()
    for args, said in ((["--sensor-noise", "nan", "--initial", "1,1", "--changed", "1,1"],
                        "σ values and sensor noise must be positive numbers"),
                       (["--seeds", "0"], "--seeds must be ≥ 1")):
        with pytest.raises(SystemExit) as e:
            main(["experiment", "thesis", *args])
        assert e.value.code == 2
        assert capsys.readouterr().err.strip().splitlines() == [f"adaptnav experiment: {said}"]


def test_replay_of_a_folder_says_it_is_a_folder(capsys, tmp_path):
    """A folder of logs given to replay was "log not found" — it is there; now it says what it is."""
    assert main(["replay", str(tmp_path), "--out", str(tmp_path / "out")]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"adaptnav replay: {tmp_path} is a folder, not a log: give one of its .mcap, .tlog or .bin files"]


def test_an_output_that_cannot_be_written_is_one_line_before_the_work(capsys, tmp_path):
    """``simulate --out`` a folder, or under a file; ``replay --out`` a file: a traceback after
    the whole simulation or replay; now one line, exit 2, before any of it."""
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    for out, said in ((tmp_path, "is a folder"), (blocker / "x.mcap", "its folder cannot be made (")):
        assert main(["simulate", "short", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"adaptnav simulate: --out {out}: {said}"), err
    assert main(["record", "--out", str(tmp_path), "--duration", "1"]) == 2  # (before connecting)
    assert capsys.readouterr().err.strip().splitlines() == [f"adaptnav record: --out {tmp_path}: is a folder"]
    with pytest.raises(SystemExit) as e:
        main(["experiment", "thesis", "--seeds", "1", "--initial", "1,1", "--changed", "1,1",
              "--plots", str(blocker)])
    assert e.value.code == 2 and capsys.readouterr().err.strip().splitlines() == [
        f"adaptnav experiment: --plots {blocker}: cannot make the folder (a file is there)"]
    assert main(["replay", "--scenario", "short", "--out", str(blocker), "--no-plots"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"adaptnav replay: --out {blocker}: cannot make the output folder (a file is there)"], err


def test_heartbeat_says_which_stage_a_long_command_is_in(capsys):
    """``adaptnav bench service`` runs for minutes: its heartbeat lines name the part that runs
    (``console.stage``), not only "running"; the stage ends with the block."""
    from adaptnav.service import console

    console.setup_logging(logging.WARNING)
    seen: list[str] = []

    def lines_with(text: str) -> bool:  # what the heartbeat thread has printed so far
        seen.extend(capsys.readouterr().err.splitlines())
        return any(text in line for line in seen)

    with console.heartbeat("bench service", period_s=0.001):
        deadline = time.monotonic() + 60.0  # a condition awaited, not a pace
        while not lines_with("bench service: running, "):
            assert time.monotonic() < deadline
            time.sleep(0.001)
        console.stage("latency (3 of 8)")
        while not lines_with("bench service: latency (3 of 8), "):
            assert time.monotonic() < deadline, seen[-3:]
            time.sleep(0.001)
    assert console._state["stage"] == ""  # the next command's heartbeat starts as "running"


def test_lifecycle_events_once_each_and_as_json(tmp_path):
    res = _run(["-v", "--log-json", "replay", "--scenario", "short", "--set", "duration_s=300",
                "--out", str(tmp_path / "r"), "--no-plots", "--no-progress"])
    assert res.returncode == 0, res.stderr
    events = []
    for line in res.stderr.splitlines():
        doc = json.loads(line)  # every log line is a JSON object
        assert {"ts", "level", "logger", "msg"} <= set(doc)
        if "event" in doc:
            events.append(doc)
    names = [e["event"] for e in events]
    assert names.count("aligned") == 1
    # validity is logged on each change, once: valid and invalid alternate, starting valid
    validity = [n for n in names if n in ("solution_valid", "solution_invalid")]
    assert validity and validity[0] == "solution_valid"
    assert all(a != b for a, b in zip(validity, validity[1:]))
    assert names.count("fix_accepted") == len({e["source"] for e in events if e["event"] == "fix_accepted"}) >= 1
    # one line per event, not one per sample: the 300 s mission has 10 USBL fixes and 3000 states
    assert len(events) < 20


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_busy_port_is_one_line_and_exit_2(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = _run(["run", "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--set", f'state_dir="{tmp_path}"',
                    "--set", "calibrator.enabled=false"])
    assert res.returncode == 2
    errors = [ln for ln in res.stderr.splitlines() if " ERROR " in ln]
    assert len(errors) == 1 and "Address already in use" in errors[0] and f":{port}" in errors[0]
    assert "Traceback" not in res.stderr and " at /" not in errors[0]


def test_unreachable_router_is_one_line_and_exit_2(tmp_path):
    port = _free_port()  # nobody listens there
    res = _run(["run", "--set", "zenoh.mode=client", "--set", f'zenoh.connect=["tcp/127.0.0.1:{port}"]',
                "--set", "zenoh.listen=[]", "--set", "zenoh.connect_timeout_s=1.0", "--set", f'state_dir="{tmp_path}"',
                "--set", "calibrator.enabled=false"])
    assert res.returncode == 2
    errors = [ln for ln in res.stderr.splitlines() if " ERROR " in ln]
    assert len(errors) == 1 and f"127.0.0.1:{port}" in errors[0], res.stderr
    assert "Traceback" not in res.stderr


def test_ctrl_c_stops_cleanly_without_traceback_from_any_process(tmp_path):
    """A terminal's Ctrl-C sends SIGINT to the whole process group: the daemon *and* its
    calibrator child. Only the daemon acts on it; nobody prints a traceback."""
    port = _free_port()
    proc = subprocess.Popen(ADAPTNAV + ["run", "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]',
                                        "--set", f'state_dir="{tmp_path}"'],
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines = []
    try:
        for line in proc.stderr:  # wait for the daemon (and its calibrator child) to be up
            lines.append(line)
            if "daemon up" in line:
                break
        os.killpg(proc.pid, signal.SIGINT)
        rest = proc.stderr.read()
        rc = proc.wait(60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = "".join(lines) + rest
    assert "calibrator process started" in err and "daemon up" in err
    assert rc == 0, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert "adaptnav daemon stopped" in err and "state saved" in err


def test_compare_explains_a_wrong_model_that_beats_the_given_one():
    from adaptnav.service.commands.replay import compare_note

    rows = {"pure_ins": {"drift_percent_since_fix": 300.0},
            "static_wrong": {"drift_percent_since_fix": 0.41}, "given": {"drift_percent_since_fix": 0.45}}
    note = compare_note(rows, {"static_wrong": 1.003, "given": 1.001}, 0.1)
    assert "k_V × 1.1" in note and "0.41 vs 0.45" in note and "1.0030 (wrong) vs 1.0010 (given)" in note
    assert "k_speed" in note and "seeds" in note
    rows["given"]["drift_percent_since_fix"] = 0.40  # the given model wins: nothing to explain
    assert compare_note(rows, {}, 0.1) == ""


def test_a_calibrator_child_that_dies_stops_the_replay_in_one_error(capsys, caplog, tmp_path, monkeypatch):
    """Replay's calibrator child killed (the OOM killer, a crash in it): the runner took each
    of its errors as one bad item, logged them and went on, repacking a batch that never left;
    an hour's log then ran for tens of minutes, and ended in a traceback. Now the replay stops
    at the first, says so in one error, and exits 1 with the files it wrote."""
    import logging

    from adaptnav.service import compose

    made = compose.make_lagged_calibrator

    def with_its_child_killed(*args, **kwargs):
        calibrator = made(*args, **kwargs)
        child = calibrator.backend._proc  # a real child process, really killed
        child.kill()
        child.join(30.0)
        assert child.exitcode == -9
        return calibrator

    monkeypatch.setattr(compose, "make_lagged_calibrator", with_its_child_killed)
    out = tmp_path / "out"
    with caplog.at_level(logging.ERROR, logger="adaptnav"):
        code = main(["replay", "--scenario", "short", "--calibrate", "--out", str(out), "--no-plots", "--no-progress"])
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("adaptnav replay: calibrator process "), err
    assert "(exit code -9)" in err[0] and err[0].endswith(f"the files in {out} hold only what came before"), err
    assert not [r for r in caplog.records if "error handling" in r.getMessage()]  # not item after item
    assert (out / "trajectory.csv").is_file()


def test_record_gives_the_signal_handlers_back(tmp_path):
    """``adaptnav record`` run in-process left its SIGTERM/SIGINT handlers (they only set its
    stop event) installed for good, refused or done: a child forked afterwards inherited them,
    and a log reader stopped by ``terminate`` never ended (test_reader). Both come back now."""
    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.transport.bus import Bus

    from .test_daemon_support import free_port

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    assert main(["record", "--out", str(tmp_path / "refused.mcap"), "--duration", "nan"]) == 2
    assert {s: signal.getsignal(s) for s in before} == before
    port = free_port()
    peer = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "auv")
    try:  # a recording that connects and ends by its duration
        assert main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--duration", "0.2",
                     "--out", str(tmp_path / "done.mcap")]) == 0
    finally:
        peer.close()
    assert (tmp_path / "done.mcap").is_file()
    assert {s: signal.getsignal(s) for s in before} == before


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device every write to fails: disk full)")
def test_a_replay_whose_output_cannot_be_written_stops_in_one_error(capsys, caplog, tmp_path):
    """A full disk under ``replay --out``: every later item failed in its turn (logged, with a
    traceback, ten times), the run went on without its product and died at summary.json in a
    traceback. Now the first failed write stops the replay: one line naming the file, exit 1.
    The output is a real device that refuses every write (``/dev/full``: ENOSPC)."""
    import logging

    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.csv").symlink_to("/dev/full")
    with caplog.at_level(logging.ERROR, logger="adaptnav"):
        code = main(["replay", "--scenario", "short", "--out", str(out), "--no-plots", "--no-progress"])
    assert code == 1
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "WARNING" not in line]
    assert err == [f"adaptnav replay: cannot write {out / 'trajectory.csv'}: No space left on device; "
                   f"the replay stopped there: the files in {out} hold only what came before"], err
    assert not [r for r in caplog.records if "error handling" in r.getMessage() or r.exc_info]
    assert not (out / "summary.json").exists()  # (no summary of a run that did not end)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device every write to fails: disk full)")
def test_simulate_and_record_onto_a_full_disk_say_so_in_one_line(capsys, tmp_path):
    """``simulate --out`` and ``record --out`` on a full disk ended in a traceback (after the
    whole simulation); now one line naming the file, exit 1. The file is a real device that
    refuses every write (``/dev/full``: ENOSPC)."""
    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.transport.bus import Bus

    from .test_daemon_support import free_port

    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")
    assert main(["simulate", "short", "--out", str(full), "--no-progress"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"adaptnav simulate: cannot write {full}: No space left on device"]
    port = free_port()
    peer = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "auv")
    try:
        assert main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--duration", "0.2", "--out", str(full)]) == 1
    finally:
        peer.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"adaptnav record: cannot write {full}: No space left on device; the recording stopped there", err
