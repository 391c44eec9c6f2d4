"""Kernels compiled ahead of time (adaptnav.kernels) behave as the just-in-time ones."""
from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest

from adaptnav import kernels
from adaptnav.calibration._kernels import heading_loglik
from adaptnav.fusion import kalman
from adaptnav.fusion.state import ACC_R, ACC_RF, ACC_SIZE, ACC_T, N_ERR, X_POS, initial_nominal


def _inputs():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((N_ERR, N_ERR))
    P = a @ a.T + N_ERR * np.eye(N_ERR)
    acc = np.zeros(ACC_SIZE)
    acc[ACC_RF] = rng.standard_normal(3) * 0.05     # Σ R f δt
    acc[ACC_R] = np.eye(3).ravel() * 0.05           # Σ R δt
    acc[ACC_T] = 0.05                               # Σ δt
    return P, acc, rng.uniform(1e-6, 1e-3, N_ERR)


def test_arguments_of_other_types_than_built_for_give_the_same_result():
    """A compiled function reads its arrays as built (contiguous float64): a strided or
    Fortran-ordered array, or a read-only one, must go to the just-in-time version
    instead of being read as if contiguous."""
    P, acc, q = _inputs()
    ref = kalman.propagated_covariance(P, acc, q)
    assert np.all(np.isfinite(ref)) and not np.allclose(ref, P)
    wide = np.zeros((ACC_SIZE, 2))
    wide[:, 0] = acc
    np.testing.assert_array_equal(kalman.propagated_covariance(P, wide[:, 0], q), ref)
    poses = np.random.default_rng(4).uniform(-3.0, 3.0, (50, 3))
    ref_h = heading_loglik(poses, 0.3, 0.1, np.log(0.1), 0.5 * np.log(2 * np.pi))
    np.testing.assert_array_equal(heading_loglik(np.asfortranarray(poses), 0.3, 0.1, np.log(0.1),
                                                 0.5 * np.log(2 * np.pi)), ref_h)
    readonly = q.copy()
    readonly.flags.writeable = False
    np.testing.assert_array_equal(kalman.propagated_covariance(P, acc, readonly), ref)


def test_a_kernel_calling_one_of_another_module_gives_the_same_result_just_in_time():
    """kalman.propagate_core calls strapdown.strapdown_step: when an argument sends it to the
    just-in-time version (a read-only array), that version must call strapdown's kernel
    just in time too (the compiled one cannot be called from numba code)."""
    rng = np.random.default_rng(5)
    n = 50
    t = np.arange(1, n + 1) * 0.01
    f = np.tile([0.1, 0.0, -9.80665], (n, 1)) + 0.01 * rng.standard_normal((n, 3))
    w = 0.01 * rng.standard_normal((n, 3))
    q = rng.uniform(1e-6, 1e-3, N_ERR)

    def run(qdiag):
        core = np.zeros(kalman.CORE_SIZE)
        core[kalman.CORE_X] = initial_nominal()
        core[kalman.CORE_CLOCK] = 0.0
        kalman.propagate_core(t, f, w, core, qdiag, 0.1)
        return core

    ref = run(q)
    assert np.all(np.isfinite(ref)) and ref[kalman.CORE_X][X_POS][0] != 0.0
    readonly = q.copy()
    readonly.flags.writeable = False
    np.testing.assert_array_equal(run(readonly), ref)
    if kernels.using_aot():
        # (from numba's on-disk cache the above passes either way: a fresh cache needs this)
        from numba.core.dispatcher import Dispatcher

        assert isinstance(kernels._jit_namespace("adaptnav.fusion.kalman")["strapdown_step"], Dispatcher)


def test_the_service_path_does_not_import_numba_when_compiled_ahead_of_time():
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    code = ("import sys, adaptnav.service.daemon, adaptnav.calibration.online, adaptnav.service.calibrator.lagged, adaptnav.service.calibrator.live;"
            "print(sorted(m for m in ('numba', 'llvmlite') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_a_replay_with_every_aid_runs_no_kernel_just_in_time(tmp_path):
    """Every kernel the filter calls from Python is in the ahead-of-time build: a replay with the
    IMU, depth, heading, DVL, RPM and USBL (the commonest compiled paths, and the zero-velocity
    and learned-velocity updates) never imports numba. A kernel with two call signatures
    the build cannot widen into one is left out of it silently (``kernels.build``) and then
    compiles just in time on its first call, in every process: stop 41's depth update did,
    at 360 µs a sample."""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    code = ("import sys; from adaptnav.service.runtime.replay import build_config, open_scenario, replay;"
            "inp = open_scenario('survey', ['dvl.enabled=true', 'sonar.enabled=false', 'duration_s=240',"
            " 'usbl.period_s=30', 'usbl.start_s=30']);"
            f"r = replay(inp, build_config(inp.scenario), {str(tmp_path)!r}, progress=False, plots=False);"
            "print(sorted(m for m in ('numba', 'llvmlite') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout
    status = (tmp_path / "aid_status.csv").read_text()
    for source in ("depth", "heading", "dvl", "learned_velocity", "usbl"):
        assert f",{source},1," in status, source  # each aid was fused at least once


def test_the_guard_takes_the_compiled_function_only_for_the_types_it_was_built_for():
    """adaptnav.kernels._guarded, the test in front of every compiled kernel: contiguous
    writeable float64 arrays of the built dimensions and scalars of the built kinds go to
    the compiled function; anything else (dtype, byte order, ndim, order, read-only, a scalar
    of another kind, another number of arguments) to the just-in-time fallback."""
    specs = [("array", "d", 2, True), ("array", "d", 1, False), ("float", None, None, None),
             ("int", None, None, None), ("bool", None, None, None)]
    call = kernels._guarded(lambda *a: "compiled", specs, lambda *a: "fallback")
    m, v = np.zeros((3, 3)), np.zeros(4)
    assert call(m, v, 0.5, 2, True) == "compiled"
    assert call(m, v[::2], np.float64(0.5), np.int64(2), np.bool_(False)) == "compiled"  # v: any order
    readonly = np.zeros(4)
    readonly.flags.writeable = False
    unpickled = pickle.loads(pickle.dumps(m))  # an equal dtype, another object (the child's batches)
    assert unpickled.dtype is not m.dtype and call(unpickled, v, 0.5, 2, True) == "compiled"
    for args in ((m.astype(np.float32), v, 0.5, 2, True), (v, v, 0.5, 2, True), (m.T, v, 0.5, 2, True),
                 (m.astype(">f8"), v, 0.5, 2, True), (m, v.astype(">f8"), 0.5, 2, True),  # same char 'd'
                 (m.astype(np.int64), v, 0.5, 2, True),
                 (m, readonly, 0.5, 2, True), (m, v, "0.5", 2, True), (m, v, 0.5, 2.0, True),
                 (m, v, 0.5, 2, None), (m, v, 0.5, 2), (list(m), v, 0.5, 2, True)):
        assert call(*args) == "fallback"
    assert kernels._guarded(lambda: "compiled", [], lambda: "fallback")() == "compiled"
    assert kernels._guarded(lambda *a: "compiled", [("other", None, None, None)], lambda *a: "fallback")(1) \
        == "fallback"


def test_the_service_path_does_not_import_scipy_stats():
    """scipy.stats costs each service process ~20 MB of resident memory (issue 17's budget is
    250 MB for the daemon and its calibrator together); its χ² quantiles come from the special
    function it calls (:func:`adaptnav.fusion.integrity.chi2_quantile`)."""
    code = ("import sys, adaptnav.service.daemon, adaptnav.fusion.eskf, adaptnav.service.compose, "
            "adaptnav.service.loop_closures, adaptnav.service.calibrator.live, adaptnav.sonar.association;"
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stdout


def test_the_daemons_side_scan_path_does_not_import_the_detectors_libraries():
    """The daemon places and associates side-scan sightings (sonar.association, the sighting
    type and ``with_navigation`` of sonar.objects); the detector that needs scipy.ndimage and
    OpenCV runs in the calibrator child (~15 MB resident the daemon does not carry)."""
    code = ("import sys, adaptnav.service.loop_closures, adaptnav.sonar.association;"
            "from adaptnav.sonar.objects import ObjectDetectorConfig, ObjectSighting, with_navigation;"
            "print(sorted(m for m in ('cv2', 'scipy.ndimage') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


_PROBE = """
import json, sys
from pathlib import Path
import numpy as np
from adaptnav import kernels
if sys.argv[1] == "only":  # the damaged build the only place looked in (no good one to fall back on)
    kernels.kernel_dirs = lambda: [Path(sys.argv[2])]
from adaptnav.fusion import kalman
core = np.zeros(kalman.CORE_SIZE)
core[kalman.CORE_P] = np.eye(kalman.N_ERR).ravel()
print(json.dumps({"aot": str(kernels.loaded_aot_path()), "error": kernels.aot_error,
                  "core_ok_deferred": isinstance(kalman.core_ok, kernels._Deferred),
                  "flush_deferred": isinstance(kalman.flush_core, kernels._Deferred),
                  "core_ok": bool(kalman.core_ok(core, 1.0))}))
"""


def _probe(kernel_dir, only: bool) -> dict:
    import json
    import os

    env = dict(os.environ, ADAPTNAV_KERNEL_DIR=str(kernel_dir))
    env.pop("ADAPTNAV_KERNELS", None)
    out = subprocess.run([sys.executable, "-c", _PROBE, "only" if only else "all", str(kernel_dir)],
                         capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1]) | {"stderr": out.stderr}


def _damaged_copy(tmp_path, damage: str):
    """The compiled module and its specs copied into ``tmp_path``, damaged as ``damage`` says."""
    import json
    import shutil

    so = kernels.loaded_aot_path()
    specs = so.with_name(so.name.split(".")[0] + ".json")
    shutil.copy(so, tmp_path / so.name)
    text = specs.read_text()
    if damage == "specs_cut_short":
        text = text[: len(text) // 2]
    elif damage == "specs_not_an_object":
        text = json.dumps(list(json.loads(text)))
    elif damage == "module_cut_short":
        (tmp_path / so.name).write_bytes(so.read_bytes()[: so.stat().st_size // 3])
    elif damage == "specs_name_a_kernel_the_module_lacks":
        d = json.loads(text)
        d["adaptnav_fusion_kalman__no_such_kernel"] = d[kernels.exported_name("adaptnav.fusion.kalman", "core_ok")]
        text = json.dumps(d)
    elif damage == "specs_without_core_ok":
        d = json.loads(text)
        del d[kernels.exported_name("adaptnav.fusion.kalman", "core_ok")]
        text = json.dumps(d)
    elif damage == "built_on_a_cpu_with_more":
        # the build's CPU had an extension this one lacks (the record as it would be written there)
        d = json.loads(text)
        d[kernels._BUILD_CPU] = ["host", *sorted(kernels.cpu_features() | {"numpy:AVX512_BEYOND"})]
        text = json.dumps(d)
    elif damage == "built_without_a_cpu_record":
        d = json.loads(text)
        del d[kernels._BUILD_CPU]
        text = json.dumps(d)
    elif damage == "built_portable":
        d = json.loads(text)
        d[kernels._BUILD_CPU] = ["portable"]
        text = json.dumps(d)
    (tmp_path / specs.name).write_text(text)
    return so


_DAMAGE = ["specs_cut_short", "specs_not_an_object", "module_cut_short", "specs_name_a_kernel_the_module_lacks",
           "built_on_a_cpu_with_more", "built_without_a_cpu_record"]


@pytest.mark.parametrize("damage", _DAMAGE)
def test_a_damaged_compiled_module_runs_the_kernels_just_in_time(tmp_path, damage):
    """Power lost while ``adaptnav warmup`` wrote the compiled kernels (or a disk that returned
    garbage) must not keep the filter from starting: the module is not used, the kernels run
    just in time, the reason is logged and kept (``kernels.aot_error``)."""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = _damaged_copy(tmp_path, damage)
    got = _probe(tmp_path, only=True)
    assert got["aot"] == "None" and got["error"] and str(tmp_path / so.name) in got["error"], got
    assert "compiled kernels unusable, running them just in time" in got["stderr"], got["stderr"]
    assert got["core_ok"] is True  # the filter's kernels work, just in time


def test_a_module_built_for_a_cpu_with_more_than_this_one_is_not_loaded(tmp_path):
    """A build for a CPU with an extension this one lacks (AVX-512 here, an SD card image of a
    Pi 5 in a Pi 4) would stop the process with an illegal instruction at its first kernel
    call: it is passed over, saying which extensions are missing, and the kernels run just in
    time. (Shown for real under an emulated CPU without AVX-512: docs/measurements.md.)"""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    _damaged_copy(tmp_path, "built_on_a_cpu_with_more")
    got = _probe(tmp_path, only=True)
    assert got["aot"] == "None" and "built for another CPU, with numpy:AVX512_BEYOND, which this one lacks" \
        in got["error"], got
    assert got["core_ok"] is True


def test_the_build_records_what_this_cpu_offers_and_a_portable_one_runs_on_any():
    """The installed build (``adaptnav warmup``, for this CPU) records every extension this CPU
    offers, so that the same files on another CPU are checked against them; a build recorded
    as portable loads whatever this CPU offers."""
    import json

    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = kernels.loaded_aot_path()
    record = json.loads(so.with_name(so.name.split(".")[0] + ".json").read_text())[kernels._BUILD_CPU]
    assert record[0] == "host" and set(record[1:]) == set(kernels.cpu_features()), record
    assert any(name.startswith("numpy:") for name in record[1:])  # numpy's detection was read
    kernels._check_cpu(["portable"])
    with pytest.raises(ValueError, match="another CPU, with numpy:NO_SUCH"):
        kernels._check_cpu(["host", *record[1:], "numpy:NO_SUCH"])


def test_a_portable_build_is_used_on_this_cpu(tmp_path):
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = _damaged_copy(tmp_path, "built_portable")
    got = _probe(tmp_path, only=True)
    assert got["aot"] == str(tmp_path / so.name) and got["error"] is None, got


@pytest.mark.parametrize("damage", _DAMAGE[::3])
def test_a_damaged_compiled_module_is_passed_over_for_a_good_one_further_on(tmp_path, damage):
    """The unit's build in ADAPTNAV_KERNEL_DIR damaged, the install's in the package good: the
    package's is used (no minute of compiling at a boot at sea), the damaged one reported."""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = _damaged_copy(tmp_path, damage)
    got = _probe(tmp_path, only=False)
    assert got["aot"] == str(so) and str(tmp_path / so.name) in got["error"], got
    assert f"compiled kernels unusable, using {so}" in got["stderr"], got["stderr"]
    assert got["core_ok_deferred"] is False and got["core_ok"] is True
    # the next warmup removes the damaged one (and builds nothing: a good one is there)
    import os

    env = dict(os.environ, ADAPTNAV_KERNEL_DIR=str(tmp_path))
    env.pop("ADAPTNAV_KERNELS", None)
    out = subprocess.run([sys.executable, "-m", "adaptnav", "warmup"], capture_output=True, text=True, env=env,
                         check=True)
    assert f"removed the unusable build {tmp_path / so.name}" in out.stdout, out.stdout
    assert not list(tmp_path.glob("_aot_kernels_*")), list(tmp_path.iterdir())
    assert _probe(tmp_path, only=False)["error"] is None


def test_a_kernel_missing_from_the_specs_alone_runs_just_in_time(tmp_path):
    """Specs without one kernel (a build that left it out): that kernel just in time, the
    others compiled — never a compiled function called without the guard of its specs."""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = _damaged_copy(tmp_path, "specs_without_core_ok")
    got = _probe(tmp_path, only=True)
    assert got["aot"] == str(tmp_path / so.name) and got["error"] is None, got
    assert got["core_ok_deferred"] is True and got["flush_deferred"] is False, got
    assert got["core_ok"] is True


def test_the_specs_are_as_readable_as_the_compiled_module():
    """The build writes the specs atomically through a temporary file (owner-only by
    default): a service running as another user than the build must still read them."""
    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (run `adaptnav warmup`)")
    so = kernels.loaded_aot_path()
    specs = so.with_name(so.name.split(".")[0] + ".json")
    assert specs.stat().st_mode & 0o444 == so.stat().st_mode & 0o444


def test_a_big_endian_array_is_not_read_as_a_native_one():
    """The compiled median window written into a big-endian buffer: the guard let it through
    (same dtype character) and the kernel wrote native bytes into it (1.5 read back as
    3e-319). Now it goes to the just-in-time version, which refuses that byte order or
    computes right — never a wrong number."""
    native = np.zeros(2 + 2 * 10)
    big = np.zeros(2 + 2 * 10, dtype=">f8")
    assert kalman.median_window_push(native, 1.5) == (1, 1.5)
    try:
        out = kalman.median_window_push(big, 1.5)
    except Exception as e:  # noqa: BLE001 — numba's typing error for a non-native byte order
        assert "byte order" in str(e).lower() or "non-native" in str(e).lower() or "dtype" in str(e).lower(), e
    else:
        assert out == (1, 1.5)
        np.testing.assert_array_equal(big.astype(float), native)


_BUILD_ONE = """
import sys
import numpy as np
from adaptnav import kernels
from adaptnav.fusion import kalman

def warm_up():
    core = np.zeros(kalman.CORE_SIZE)
    core[kalman.CORE_P] = np.eye(kalman.N_ERR).ravel()
    kalman.core_ok(core, 1.0)

print(kernels.build(warm_up, portable=sys.argv[1] == "portable"))
"""


def _instructions(so) -> str:
    import shutil

    if shutil.which("objdump") is None:
        return ""
    return subprocess.run(["objdump", "-d", str(so)], capture_output=True, text=True, check=True).stdout


def test_a_portable_build_takes_only_the_architectures_baseline(tmp_path):
    """``adaptnav warmup --portable`` (the container image's build: it runs on CPUs other than the
    builder's) records itself as portable and uses no instruction set extension; the build for
    this CPU uses this CPU's (AVX registers on an x86-64 that has them)."""
    import json
    import os
    import platform

    if not kernels.using_aot():
        pytest.skip("kernels not compiled ahead of time (no C and C++ compiler for numba.pycc?)")
    built = {}
    for kind in ("portable", "host"):
        d = tmp_path / kind
        env = dict(os.environ, ADAPTNAV_KERNELS="jit", ADAPTNAV_KERNEL_DIR=str(d), NUMBA_CACHE_DIR=str(d / "jit"))
        out = subprocess.run([sys.executable, "-c", _BUILD_ONE, kind], capture_output=True, text=True, env=env,
                             check=True)
        so = d / out.stdout.strip().splitlines()[-1].rsplit("/", 1)[-1]
        record = json.loads(so.with_name(so.name.split(".")[0] + ".json").read_text())[kernels._BUILD_CPU]
        built[kind] = (so, record)
    assert built["portable"][1] == ["portable"]
    assert built["host"][1][0] == "host" and set(built["host"][1][1:]) == set(kernels.cpu_features())
    if platform.machine() in ("x86_64", "AMD64") and "numpy:AVX2" in kernels.cpu_features():
        host_code, portable_code = (_instructions(built[k][0]) for k in ("host", "portable"))
        if not host_code:
            pytest.skip("no objdump to read the instructions with")
        assert "%ymm" in host_code or "%zmm" in host_code  # (this CPU's extensions are used)
        assert "%ymm" not in portable_code and "%zmm" not in portable_code


def test_a_build_without_a_compiler_says_so_before_the_warm_up(tmp_path):
    """numba.pycc needs a C and a C++ compiler; without them the build stops before the warm-up
    (minutes of compiling just in time on a Pi, wasted), saying what is missing."""
    import os

    code = ("from adaptnav import kernels\n"
            "try:\n"
            "    kernels.build(lambda: print('WARMED'))\n"
            "except RuntimeError as e:\n"
            "    print('ERROR', e)\n")
    env = dict(os.environ, ADAPTNAV_KERNELS="jit", ADAPTNAV_KERNEL_DIR=str(tmp_path), CC=str(tmp_path / "no-cc"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert "WARMED" not in out and "ERROR no C and C++ compiler numba.pycc can use" in out, out
    assert not list(tmp_path.glob("_aot_kernels_*"))
