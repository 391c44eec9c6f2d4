"""Compiled kernels: ahead of time when built, else numba's just-in-time compiler.

The hot loops (:mod:`adaptnav.fusion.strapdown`, :mod:`adaptnav.fusion.kalman`,
:mod:`adaptnav.calibration._kernels`) are
numba ``njit`` functions declared with :func:`jit` instead of ``numba.njit``. Just in time,
numba costs every process that imports it ~65 MB (llvmlite's LLVM and numba's typing
registries) plus ~55–90 MB to load the cached kernels, and a fresh install compiles for
20 s here (a minute on a Raspberry Pi) before the first solution. :func:`build` (run by
``adaptnav warmup``, i.e. ``make`` and the systemd unit's ``ExecStartPre``) therefore
compiles every kernel ahead of time with ``numba.pycc`` into one extension module,
with the signatures the service really calls (recorded while the warm-up runs the
filter and one EM window just in time). When that module is present *and* built from
the current kernel sources, :func:`jit` returns its functions and numba is never
imported: same numba code generation, no JIT at run time.

The module is named after a hash of the kernel sources, the Python and the numba
version (a stale build is ignored, never used), and lives in ``ADAPTNAV_KERNEL_DIR``
when set, else next to this file. ``ADAPTNAV_KERNELS=jit`` forces just in time.

A build is for the CPU it ran on (``host``: its instruction set extensions, e.g. AVX-512;
the EM iteration is ~25 % slower without them), and such a module on a CPU without them
kills the process at its first kernel call (SIGILL: a venv or SD card image copied to
another computer, a container built on another machine, a VM moved to another host). The
specs therefore record what the build's CPU offered (:func:`cpu_features`), and a module
whose CPU offered something this one lacks is passed over like a damaged one: the kernels
run just in time, the health report says why, the next ``adaptnav warmup`` builds for this
CPU. ``build(portable=True)`` (``adaptnav warmup --portable``, for an image that runs
elsewhere) compiles for the architecture's baseline (x86-64, ARMv8-A): any CPU of it.
A compiled function does not check its arguments (a strided or integer array where it
was built for a contiguous float one reads wrong memory), so each comes with a guard:
arguments of the recorded types (dtype, dimensions, contiguous and writeable arrays;
numbers) go to the compiled code, anything else to the just-in-time version. A kernel
the build did not see called (tests, benchmarks) works the same way: on its first call
its module's kernels are compiled just in time, in a namespace of their own (where a
kernel of another kernel module it calls is that module's just-in-time version too).

Just in time, numba's on-disk cache (``cache=True``) checks a cached kernel against its own
source file only: a kernel that calls one in another file (:mod:`adaptnav.fusion.kalman`'s
propagation calls :func:`adaptnav.fusion.strapdown.strapdown_step`) would keep the old
callee compiled into it after that file changed. :func:`jit` therefore stamps every cached
kernel with the hash of all kernel sources (:func:`sources_digest`, which also names the
ahead-of-time module): any change recompiles them all, nothing stale is ever loaded.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.machinery
import json
import importlib.util
import logging
import os
import sys
import sysconfig
import types
from pathlib import Path
from typing import Any, Callable

# the modules whose kernels are declared with jit(); their sources key the compiled module
KERNEL_MODULES = ("adaptnav.fusion.strapdown", "adaptnav.fusion.kalman", "adaptnav.calibration._kernels",
                  "adaptnav.sonar._kernels")

_registry: dict[str, dict[str, tuple[Callable, dict]]] = {}   # module → name → (py_func, options)
_jit_namespaces: dict[str, dict[str, Any]] = {}
_aot: Any = False  # False: not looked up yet; None: absent


def kernel_dirs() -> list[Path]:
    """Where the compiled module is looked up: ``ADAPTNAV_KERNEL_DIR`` when set (a
    writable cache of a service whose package directory is read-only), then the
    package directory (an install step run as its owner). Built into the first."""
    env = os.environ.get("ADAPTNAV_KERNEL_DIR")
    return ([Path(env)] if env else []) + [Path(__file__).parent]


_digest: bytes | None = None


def sources_digest() -> bytes:
    """SHA-1 of the sources of :data:`KERNEL_MODULES` and of this file (how they are
    compiled: :func:`build`'s flags), read once per process."""
    global _digest
    if _digest is None:
        h = hashlib.sha1()
        for name in KERNEL_MODULES:
            spec = importlib.util.find_spec(name)
            h.update(Path(spec.origin).read_bytes())
        h.update(Path(__file__).read_bytes())
        _digest = h.digest()
    return _digest


def aot_name() -> str:
    """Module name of the compiled kernels for the current sources and toolchain."""
    from importlib.metadata import PackageNotFoundError, version

    h = hashlib.sha1(sources_digest())
    try:
        numba_version = version("numba")
    except PackageNotFoundError:
        numba_version = "none"
    h.update(f"{sys.version_info[:2]} {numba_version} {sysconfig.get_platform()}".encode())
    return f"_aot_kernels_{h.hexdigest()[:16]}"


def aot_path() -> Path:
    """Where the compiled module is built (:func:`loaded_aot_path`: the one in use)."""
    return kernel_dirs()[0] / (aot_name() + importlib.machinery.EXTENSION_SUFFIXES[0])


aot_error: str | None = None  # why a compiled module present was not used (None: it was, or none is)
passed_over: list[Path] = []  # the compiled modules found unusable (adaptnav warmup removes them)


def _load_aot() -> Any:
    """The compiled module, or None: absent, forced off, or unreadable — a module or argument
    specs cut short (power lost during ``adaptnav warmup``), of the wrong kind, not what the
    build wrote. An unreadable one is passed over for the next place (:func:`kernel_dirs`);
    none usable, the kernels run just in time. Either way :data:`aot_error` says what was
    passed over and why (logged once), and the next ``adaptnav warmup`` builds again: the
    filter must start whatever lies on the disk."""
    global _aot, aot_error
    if _aot is False:
        _aot = None
        if os.environ.get("ADAPTNAV_KERNELS", "").lower() != "jit":
            name = aot_path().name
            problems = []
            for path in (d / name for d in kernel_dirs()):
                specs_path = path.with_name(path.name.split(".")[0] + ".json")
                if not (path.is_file() and specs_path.is_file()):
                    continue
                try:
                    _aot = _load_module(path, specs_path)
                    break
                except Exception as e:  # noqa: BLE001 - any unreadable build: the next, or just in time
                    problems.append(f"{path}: {type(e).__name__}: {e}")
                    passed_over.append(path)
            if problems:
                aot_error = "; ".join(problems)
                logging.getLogger(__name__).warning(
                    "compiled kernels unusable, %s (run `adaptnav warmup` to build them again): %s",
                    "running them just in time" if _aot is None else f"using {_aot.__file__}", aot_error)
    return _aot


def _load_module(path: Path, specs_path: Path) -> Any:
    """The compiled module at ``path`` with its argument specs, checked (:func:`_load_aot`)."""
    arg_specs = json.loads(specs_path.read_text())
    if not (isinstance(arg_specs, dict) and all(isinstance(v, list) for v in arg_specs.values())):
        raise ValueError("argument specs are not a JSON object of lists")
    # the module as the build wrote it (a shorter one kills the process as it loads, SIGBUS;
    # ~1 ms for its 1.5 MB)
    if arg_specs.pop(_MODULE_DIGEST, None) != [_file_digest(path)]:
        raise ValueError("the module is not the one its specs were written for")
    build_cpu = arg_specs.pop(_BUILD_CPU, None)
    _check_cpu(build_cpu)  # before it is loaded: nothing of it runs on a CPU it was not built for
    spec = importlib.util.spec_from_file_location(path.name.split(".")[0], path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    missing = sorted(e for e in arg_specs if not callable(getattr(module, e, None)))
    if missing:
        raise ValueError(f"{len(missing)} kernels of its specs missing ({missing[0]}, ...)")
    module.arg_specs = arg_specs
    module.build_cpu = build_cpu[0]
    return module


_MODULE_DIGEST = "__module_sha256__"  # the specs' entry with the compiled module's digest
# the specs' entry with the build's target: ["portable"], or ["host", *cpu_features() of the build]
_BUILD_CPU = "__build_cpu__"


def cpu_features() -> frozenset[str]:
    """What this CPU offers that compiled code may use, each name prefixed by where it was
    read: numpy's run-time detection (``numpy:AVX2``; CPUID with the OS's consent, or the
    kernel's HWCAP on ARM; exact under an emulator too), and on ARM the instruction set
    features every core lists in ``/proc/cpuinfo`` (``cpuinfo:atomics``, LSE, and ``lrcpc``,
    which numpy does not list; x86's ``flags`` there mix in the kernel's and the hypervisor's
    own, which differ between machines with one instruction set: not read)."""
    out: set[str] = set()
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as numpy_features
    except ImportError:  # numpy < 2
        try:
            from numpy.core._multiarray_umath import __cpu_features__ as numpy_features
        except ImportError:
            numpy_features = {}
    out.update(f"numpy:{name}" for name, present in numpy_features.items() if present)
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    shared: set[str] | None = None
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "Features":
            flags = set(value.split())
            shared = flags if shared is None else shared & flags
    out.update(f"cpuinfo:{flag}" for flag in shared or ())
    return frozenset(out)


def _check_cpu(build_cpu: Any) -> None:
    """Raise ValueError unless this CPU offers everything ``build_cpu`` (the specs' entry)
    says the build's did (:func:`cpu_features`)."""
    if not (isinstance(build_cpu, list) and build_cpu and build_cpu[0] in ("host", "portable")):
        raise ValueError("no record of the CPU it was built for")
    if build_cpu[0] == "portable":
        return
    missing = sorted(set(map(str, build_cpu[1:])) - cpu_features())
    if missing:
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        raise ValueError(f"built for another CPU, with {shown}, which this one lacks (its code "
                         f"would stop the process with an illegal instruction)")


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def exported_name(module: str, name: str) -> str:
    return f"{module.replace('.', '_')}__{name}"


def using_aot() -> bool:
    """True when the kernels come from the ahead-of-time module."""
    return _load_aot() is not None


def loaded_aot_path() -> Path | None:
    """The compiled module in use (None: the kernels run just in time)."""
    aot = _load_aot()
    return None if aot is None else Path(aot.__file__)


def loaded_build() -> str | None:
    """What the compiled module in use was built for: ``"host"`` (the CPU it was built on,
    and this one offers everything that one did) or ``"portable"``; None: just in time."""
    aot = _load_aot()
    return None if aot is None else aot.build_cpu


def jit(**options: Any) -> Callable[[Callable], Any]:
    """``numba.njit(**options)``, or the ahead-of-time compiled function when built."""
    def decorate(py_func: Callable) -> Any:
        module = py_func.__module__
        _registry.setdefault(module, {})[py_func.__name__] = (py_func, options)
        aot = _load_aot()
        if aot is None:
            import numba

            return _stamp_cache(numba.njit(**options)(py_func))
        export = exported_name(module, py_func.__name__)
        compiled = getattr(aot, export, None)
        specs = aot.arg_specs.get(export)
        fallback = _Deferred(module, py_func.__name__)
        if compiled is None or specs is None:  # not built (a kernel without specs is never guessed at)
            return fallback
        out = _guarded(compiled, specs, fallback)
        out._kernel = (module, py_func.__name__)
        return out
    return decorate


def _stamp_cache(dispatcher: Any) -> Any:
    """Key ``dispatcher``'s on-disk cache on every kernel source (module docstring): numba
    compares the stamp its index was written with to this one and recompiles on a
    difference. A numba without these internals keeps its own per-file stamp."""
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = (cache_file._source_stamp, sources_digest())
    return dispatcher


def _guarded(compiled: Callable, specs: list, fallback: Callable) -> Callable:
    """``compiled`` for arguments of the types it was built for, else ``fallback``.

    Per call (the live filter makes four per IMU sample, on its latency path): the test is
    one expression per argument, written out for the kernel's types (a loop over the specs
    took ~145 bytecodes a call, a quarter of the interpreter's work on a live IMU sample),
    with concrete-type ``isinstance`` tests, not the ``numbers`` ABCs (~0.3 µs each), and an
    array's dtype compared whole (byte order included)."""
    import numpy as np

    scalar_types = {"float": (float, int, np.floating, np.integer),   # bool is an int
                    "int": (int, np.integer), "bool": (bool, np.bool_)}
    env: dict[str, Any] = {"ndarray": np.ndarray, "compiled": compiled, "fallback": fallback}
    tests = []
    for i, (kind, dtype, ndim, contiguous) in enumerate(specs):
        if kind == "array":
            # flags.carray: C-contiguous, aligned and writeable; flags.behaved: the last two
            flag = "carray" if contiguous else "behaved"
            # dtype equality, not its character: a big-endian array has the same character
            # ('>f8' is 'd') and the compiled function would read and write its bytes as
            # native ones; not identity either (an unpickled array's dtype is an equal copy)
            env[f"dtype{i}"] = np.dtype(dtype)
            tests.append(f"type(a{i}) is ndarray and a{i}.dtype == dtype{i} "
                         f"and a{i}.ndim == {int(ndim)} and a{i}.flags.{flag}")
        else:  # a kind without scalar types never matches: the fallback takes it
            env[f"types{i}"] = scalar_types.get(kind, ())
            tests.append(f"isinstance(a{i}, types{i})")
    n = len(specs)
    unpack = f"        {''.join(f'a{i}, ' for i in range(n))}= args\n" if n else ""
    exec(f"def call(*args):\n"
         f"    if len(args) == {n}:\n"
         f"{unpack}"
         f"        if {' and '.join(tests) or 'True'}:\n"
         f"            return compiled(*args)\n"
         f"    return fallback(*args)\n", env)
    call = env["call"]
    call.__name__ = call.__qualname__ = getattr(compiled, "__name__", "kernel")
    call.__wrapped__ = compiled
    return call


def unguarded(kernel: Callable) -> Callable:
    """The compiled function behind a kernel's argument guard (:func:`jit` ahead of time), else
    the kernel as it is (just in time: a numba dispatcher; a kernel the build did not see; a
    stand-in). The guard's test per argument and its call cost ~0.5–1.5 µs a call; a caller on
    a hot path skips them when every call passes what the guard would find every time: arrays
    that are the caller's own, allocated once as C-contiguous, writeable float64 of the kernel's
    dimensions (or views of such that are so too), and numbers of the kernel's types. Never for
    an array that comes from outside (a sample's, a batch's slice, an argument of a public
    function): the compiled code does not check it and reads wrong memory where the guard
    would have sent it just in time."""
    compiled = getattr(kernel, "__wrapped__", None)
    # (a guard has both; a numba dispatcher's __wrapped__ is its Python function)
    return compiled if compiled is not None and getattr(kernel, "_kernel", None) is not None else kernel


class _Deferred:
    """A kernel missing from the compiled module: compiled just in time on first call,
    with every kernel of its module, in a namespace where they call each other's
    numba versions (the module's own names are the compiled module's functions)."""

    def __init__(self, module: str, name: str) -> None:
        self.module, self.name = module, name
        self._kernel = (module, name)

    def __call__(self, *args: Any) -> Any:
        return _jit_namespace(self.module)[self.name](*args)


def _jit_namespace(module: str) -> dict[str, Any]:
    ns = _jit_namespaces.get(module)
    if ns is None:
        import numba

        ns = dict(vars(sys.modules[module]))
        for key, value in list(ns.items()):
            # a kernel imported from another kernel module: its just-in-time version (the
            # compiled one, a Python callable, cannot be called from numba code)
            origin = getattr(value, "_kernel", None) if callable(value) else None
            if isinstance(origin, tuple) and origin[0] != module:
                ns[key] = _jit_namespace(origin[0])[origin[1]]
        for name, (f, options) in _registry[module].items():
            g = types.FunctionType(f.__code__, ns, name, f.__defaults__, f.__closure__)
            g.__module__ = f.__module__
            ns[name] = numba.njit(**options)(g)
        _jit_namespaces[module] = ns
    return ns


# -- the ahead-of-time build ------------------------------------------------------------
@contextlib.contextmanager
def _declared_error_models():
    """While ``numba.pycc`` compiles: every kernel with the ``error_model`` it was declared with.
    pycc compiles all its exports with one set of flags (error model "python": a test for a
    zero divisor before every division, which keeps a loop from vectorising;
    :func:`adaptnav.sonar._kernels.local_level` took 1.42 ms ahead of time vs 0.91 ms just in
    time on a 200 x 1000 image)."""
    from numba.pycc import compiler

    declared = {f: opts["error_model"] for kernels in _registry.values() for f, opts in kernels.values()
                if "error_model" in opts}
    plain = compiler.compile_extra

    def compile_extra(typingctx, targetctx, func, args, return_type, flags, *rest, **kw):
        if func in declared:
            flags = flags.copy()
            flags.error_model = declared[func]
        return plain(typingctx, targetctx, func, args, return_type, flags, *rest, **kw)

    compiler.compile_extra = compile_extra
    try:
        yield
    finally:
        compiler.compile_extra = plain


def _widen(sigs: list) -> Any:
    """One signature accepting every recorded call: arrays of differing layout become
    'A' (any layout); anything else differing → None (the kernel stays just in time)."""
    from numba.core import types as nt

    args = list(sigs[0][0])
    ret = sigs[0][1]
    for a_args, a_ret in sigs[1:]:
        if len(a_args) != len(args) or a_ret != ret:
            return None
        for i, (x, y) in enumerate(zip(args, a_args)):
            if x == y:
                continue
            if isinstance(x, nt.Array) and isinstance(y, nt.Array) and x.dtype == y.dtype and x.ndim == y.ndim:
                args[i] = x.copy(layout="A")
            else:
                return None
    return ret(*args)


def _arg_spec(t: Any) -> list | None:
    """What the guard checks for numba type ``t``; None when it cannot be checked."""
    from numba.core import types as nt

    if isinstance(t, nt.Array):
        if t.mutable is False or not t.aligned or t.layout not in ("C", "A"):
            return None
        try:
            import numpy as np

            char = np.dtype(str(t.dtype)).char
        except TypeError:
            return None
        return ["array", char, t.ndim, t.layout == "C"]
    if isinstance(t, nt.Boolean):
        return ["bool", "", 0, False]
    if isinstance(t, nt.Float) and t.bitwidth == 64:
        return ["float", "", 0, False]
    if isinstance(t, nt.Integer) and t.signed and t.bitwidth == 64:
        return ["int", "", 0, False]
    return None


@contextlib.contextmanager
def _this_cpus_features():
    """While ``numba.pycc`` compiles for ``host``: the instruction set extensions this CPU has,
    as numba's just-in-time code takes them. pycc takes only the CPU model's name, and with it
    the model's extensions, more than a VM or a kernel may leave on (AVX-512 masked): the code
    would then need what :func:`cpu_features` does not show. A numba without this hook keeps
    its own choice."""
    from numba.core import codegen

    aot = getattr(codegen, "AOTCPUCodegen", None)
    plain = getattr(aot, "_customize_tm_features", None)
    if plain is None or not hasattr(codegen, "get_host_cpu_features"):
        yield
        return

    def features(self):
        return codegen.get_host_cpu_features() if getattr(self, "_cpu_name", "") == "host" else plain(self)

    aot._customize_tm_features = features
    try:
        yield
    finally:
        aot._customize_tm_features = plain


def build(warm_up: Callable[[], None], verbose: bool = False, portable: bool = False) -> Path:
    """Record the kernels' signatures while ``warm_up()`` runs them just in time (in
    this process, which must not have loaded a compiled module), then compile them
    ahead of time into :func:`aot_path` for this CPU, or with ``portable`` for any CPU of
    its architecture (an image to run elsewhere; module docstring). Returns the path."""
    if using_aot():
        raise RuntimeError("build() needs the kernels just in time: set ADAPTNAV_KERNELS=jit")
    try:
        from numba.pycc.platform import external_compiler_works
    except ImportError:  # a numba without it: its own error, after the warm-up
        external_compiler_works = None
    if external_compiler_works is not None and not external_compiler_works():
        # said before the warm-up (minutes on a Pi), not in numba's words (which suggest conda)
        raise RuntimeError("no C and C++ compiler numba.pycc can use (it needs both: gcc and g++ on Debian)")
    for name in KERNEL_MODULES:
        importlib.import_module(name)
    warm_up()
    import warnings

    from numba.core.errors import NumbaPendingDeprecationWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaPendingDeprecationWarning)
        from numba.pycc import CC

    path = aot_path()
    cc = CC(path.name.split(".")[0])
    cc.output_dir = str(path.parent)
    cc.target_cpu = "" if portable else "host"  # "": the architecture's baseline
    cc.verbose = verbose
    arg_specs: dict[str, list] = {}
    for module in KERNEL_MODULES:
        mod = sys.modules[module]
        for name in _registry.get(module, {}):
            dispatcher = getattr(mod, name)
            sigs = [(s.args, s.return_type) for s in
                    (cres.signature for cres in dispatcher.overloads.values())]
            sig = _widen(sigs) if sigs else None
            specs = [_arg_spec(t) for t in sig.args] if sig is not None else [None]
            if sig is not None and None not in specs:
                export = exported_name(module, name)
                cc.export(export, sig)(dispatcher.py_func)
                arg_specs[export] = specs
            elif sigs and not name.startswith("_"):
                # a public kernel is called from Python: left out, it would compile just in time
                # in every process, silently (a private helper is compiled into its callers)
                print(f"adaptnav warmup: {module}.{name} is not compiled ahead of time (its calls' "
                      f"signatures do not widen to one the guard can check: {[str(s[0]) for s in sigs]})",
                      file=sys.stderr)
    path.parent.mkdir(parents=True, exist_ok=True)
    specs_path = path.with_name(path.name.split(".")[0] + ".json")
    # the specs mark a build complete: gone while the module is rewritten, then written whole
    # (atomically), so that a build cut short leaves nothing that looks complete
    specs_path.unlink(missing_ok=True)
    with warnings.catch_warnings(), _declared_error_models(), _this_cpus_features():
        warnings.simplefilter("ignore")
        cc.compile()
    arg_specs[_MODULE_DIGEST] = [_file_digest(path)]
    arg_specs[_BUILD_CPU] = ["portable"] if portable else ["host", *sorted(cpu_features())]
    from adaptnav.files import atomic_write_bytes

    # readable by whoever may load the module (a service user, the build run as root)
    atomic_write_bytes(specs_path, json.dumps(arg_specs, indent=1, sort_keys=True).encode(),
                       mode=path.stat().st_mode & 0o666)
    for stale in path.parent.glob("_aot_kernels_*"):
        if stale.name not in (path.name, specs_path.name):
            stale.unlink(missing_ok=True)
    return path
