"""The suite's xdist groups hold: ``make test`` runs ``-n 2 --dist loadgroup``, and the tests of
one ``xdist_group`` (those holding the CPU wake-up bound, those sharing a module's replay of a
log) must run on one worker. pytest 9.2 with pytest-xdist 3.8 ignored every group without a word
(pytest-dev/pytest-xdist#1386): pyproject.toml keeps pytest below 9.2 until a release fixes it."""
import subprocess
import sys
import textwrap


def test_the_tests_of_an_xdist_group_run_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(textwrap.dedent("""
        import os
        import pytest

        pytestmark = pytest.mark.xdist_group("one_worker")


        @pytest.mark.parametrize("i", range(8))
        def test_where(i):
            with open(os.path.join(os.path.dirname(__file__), "workers.txt"), "a") as f:
                f.write(os.environ["PYTEST_XDIST_WORKER"] + "\\n")
        """))
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadgroup", "-p",
                           "no:cacheprovider", "--rootdir", str(tmp_path), str(tmp_path / "test_grouped.py")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    workers = (tmp_path / "workers.txt").read_text().split()
    assert len(workers) == 8 and len(set(workers)) == 1, workers
