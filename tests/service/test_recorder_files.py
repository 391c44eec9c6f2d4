"""The recorder never loses what it already wrote (issue 12 item 7): a message it cannot
write is skipped and counted, the file is finished when the writer is interrupted, and a
SIGKILLed recorder leaves a file readable up to its last complete chunk."""
from __future__ import annotations

import subprocess
import sys
import textwrap

from adaptnav.fusion.samples import DepthSample, ImuSample
from adaptnav.service.transport.logs import SKIPPED, TruncatedLogError, read_mcap, write_mcap


def _imu(n, t0=0.0):
    return [ImuSample(t0 + 0.01 * k, (0.0, 0.0, -9.8), (0.0, 0.0, 0.001 * k)) for k in range(n)]


def _read(path):
    items = list(read_mcap(path))
    return [i for i in items if not isinstance(i, Exception)], [i for i in items if isinstance(i, Exception)]


def test_a_message_stamped_1e17_and_an_unwritable_one_lose_nothing(tmp_path):
    """A depth sample stamped 1e17 s crashed the recorder; the file was unreadable."""
    msgs = _imu(50) + [DepthSample(1e17, 2e5), object(), DepthSample(0.5, 2e5)] + _imu(50, 1.0)
    counts = write_mcap(tmp_path / "r.mcap", iter(msgs))
    good, errors = _read(tmp_path / "r.mcap")
    assert errors == []
    assert counts == {"imu": 100, "depth": 2, SKIPPED: 1}
    assert len(good) == 102 and any(s.KIND == "depth" and s.t_s == 1e17 for s in good)


def test_an_interrupted_writer_still_finishes_the_file(tmp_path):
    def messages():
        yield from _imu(300)
        raise KeyboardInterrupt  # SIGINT/SIGTERM handlers end the iteration the same way

    try:
        write_mcap(tmp_path / "r.mcap", messages())
    except KeyboardInterrupt:
        pass
    good, errors = _read(tmp_path / "r.mcap")
    assert errors == [] and len(good) == 300


def test_a_sigkilled_writer_leaves_its_complete_chunks_readable(tmp_path):
    path = tmp_path / "r.mcap"
    code = textwrap.dedent(f"""
        import os, signal
        from adaptnav.fusion.samples import ImuSample
        from adaptnav.service.transport.logs import write_mcap

        def messages():
            for k in range(200000):
                yield ImuSample(0.005 * k, (0.01 * (k % 7), 0.0, -9.8), (0.0, 0.0, 1e-4 * (k % 13)))
                if k == 60000:
                    os.kill(os.getpid(), signal.SIGKILL)

        write_mcap({str(path)!r}, messages())
    """)
    proc = subprocess.run([sys.executable, "-c", code], timeout=120)
    assert proc.returncode == -9
    good, errors = _read(path)
    assert len(errors) == 1 and isinstance(errors[0], TruncatedLogError)
    # everything up to the last complete chunk (512 kB ≈ 2,800 messages) is there
    assert 60000 - 6000 <= len(good) <= 60001
    assert [s.t_s for s in good[:3]] == [0.0, 0.005, 0.01]
