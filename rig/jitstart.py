"""numba's start-up in a process that simulates or logs, without ``scipy.linalg``.

At a process's first call of a compiled kernel (cached or not), numba loads its CPU target, and
with it ``numba.np.arraymath``, which checks that BLAS is there by importing
``scipy.linalg.cython_blas``: that imports the whole ``scipy.linalg`` package (its
``scipy._lib`` array-API layer, LAPACK wrappers, decompositions), 0.1-0.25 s of a
``rig run``'s start-up that no simulation or log kernel uses.

:func:`preload_cython_blas` loads the two small extension modules numba asks for
(``scipy.linalg.cython_blas`` and ``cython_lapack``: the BLAS/LAPACK function pointers numba's
``np.dot`` and ``np.linalg`` call) from their files, without their package's ``__init__``, so
numba finds them in ``sys.modules``; numba checks their integer width against ``scipy.__config__``
as before. It does nothing once ``scipy.linalg`` is imported (an analysis process), when numba's
target is already loaded, or when the files are not where scipy keeps them (numba then imports
them its own way). A later ``import scipy.linalg`` works as usual.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import os
import platform
import sys
from pathlib import Path

_NAMES = ("cython_blas", "cython_lapack")


def preload_cython_blas() -> bool:
    """Load ``scipy.linalg.cython_blas`` / ``cython_lapack`` without ``scipy.linalg`` (see the module
    docstring). Returns True when both are in ``sys.modules`` afterwards."""
    full = [f"scipy.linalg.{n}" for n in _NAMES]
    if all(n in sys.modules for n in full):
        return True
    if aot_in_use():
        return False  # the ahead-of-time kernels need no numba (_jit_all calls this before it imports numba)
    if "scipy.linalg" in sys.modules or "numba.np.arraymath" in sys.modules:
        return False
    try:
        spec = importlib.util.find_spec("scipy")
        if spec is None or not spec.submodule_search_locations:
            return False
        folder = Path(spec.submodule_search_locations[0]) / "linalg"
        loaded = {}
        for name, mod_name in zip(_NAMES, full):
            files = [folder / (name + suffix) for suffix in importlib.machinery.EXTENSION_SUFFIXES]
            files = [f for f in files if f.is_file()]  # this interpreter's extension file names, in its order
            if not files:
                return False
            s = importlib.util.spec_from_file_location(mod_name, files[0])
            mod = importlib.util.module_from_spec(s)
            s.loader.exec_module(mod)
            loaded[mod_name] = mod
    except (ImportError, OSError):
        return False
    sys.modules.update(loaded)
    return True


# ---------------------------------------------------------------------------------------------------------
# The run path's kernels compiled ahead of time (numba.pycc), so that `rig run --sim` never imports numba
# ---------------------------------------------------------------------------------------------------------
# Every kernel of rig/model, rig/sim, rig/log and rig/control.py is declared with :func:`kernel` (numba's
# ``njit(cache=True)``, the one source of each kernel). A process that only calls the run path's entry
# kernels from Python (``rig run --sim``) calls :func:`prefer_aot` before importing them: when an extension
# module built from the same sources (:func:`build_aot`) is in the cache, :func:`kernel` then returns a
# :class:`LazyKernel` that calls the module's function, and numba is never imported (its import and CPU
# target cost 0.45-0.5 s of a 1.6 s main job). A kernel the module lacks, or arguments its signature does
# not take, turn every LazyKernel into numba's dispatcher at once (:func:`_jit_all`).

#: the entry kernels the run path calls from Python: (module, name, return type, argument codes of _ARG)
AOT_KERNELS = (
    ("rig.sim.plant", "run_closed_loop", "int64", ("f1",) * 9 + ("i", "f2", "i", "f2", "i", "i")),
    ("rig.sim.plant", "normal_forces", "UniTuple(float64, 2)", ("f1", "f")),
    ("rig.model.friction", "init_state", "void", ("f1", "f1", "f")),
    ("rig.model.friction", "mu_series", "float64[::1]", ("f1", "f1", "f1", "f1", "f")),
    ("rig.log.kernels", "block_means", "UniTuple(int64, 2)", ("f2", "b1", "f1", "f1", "f2", "i", "i", "f2")),
    ("rig.log.kernels", "flush_means", "void", ("f2", "i", "f2")),
    ("rig.log.loopblock", "_quant_pack_py", "int64",
     ("f2", "f1", "f1", "f1", "f1", "i1", "f1", "f1", "b", "u1", "i1")),
    ("rig.log.figures", "_block_stats_py", "void", ("f1",) * 7),
)
#: argument code -> numba type, and for arrays (C-contiguous) the dtype and ndim a call is checked against: a
#: pycc function takes any buffer as its declared type, unchecked (a float32 or strided array would be misread)
_ARG = {"f": ("float64", None), "i": ("int64", None), "b": ("boolean", None),
        "f1": ("float64[::1]", ("float64", 1)), "f2": ("float64[:, ::1]", ("float64", 2)),
        "i1": ("int64[::1]", ("int64", 1)), "u1": ("uint8[::1]", ("uint8", 1)), "b1": ("boolean[::1]", ("bool", 1))}


def aot_signature(ret: str, codes) -> str:
    """numba's signature string of an AOT_KERNELS entry."""
    return f"{ret}({', '.join(_ARG[c][0] for c in codes)})"


#: the sources of every kernel the entries call (under rig/): their hash keys the built module
AOT_SOURCES = ("model", "sim", "log", "control.py", "jitstart.py")
_RIG = Path(__file__).resolve().parent


class _State:
    lazy = False            # kernel() returns LazyKernels (prefer_aot found a current module)
    aot: dict = {}          # "module:name" -> the built module's function
    lazies: list = []       # every LazyKernel made, for _jit_all
    jitted = False


def aot_in_use() -> bool:
    """True in a process whose kernels come from the ahead-of-time module (nothing compiles)."""
    return _State.lazy and not _State.jitted


def aot_symbol(module: str, name: str) -> str:
    """The name of kernel ``module.name`` in the built module."""
    return module.replace(".", "_") + "__" + name.lstrip("_")


def kernel(fn=None, **options):
    """``numba.njit(cache=True, **options)(fn)`` (usable as ``@kernel`` or ``@kernel(nogil=True)``); in a
    process that called :func:`prefer_aot` successfully, a :class:`LazyKernel` instead (numba not imported)."""
    if fn is None:
        return lambda f: kernel(f, **options)
    if _State.lazy and not _State.jitted:
        k = LazyKernel(fn, options)
        _State.lazies.append(k)
        return k
    from numba import njit

    return njit(cache=True, **options)(fn)


class LazyKernel:
    """A kernel of a process that prefers the ahead-of-time module: a call goes to the module's function of
    the same name, or (a kernel the module lacks, arguments its signature does not take) to numba's
    dispatcher, made then for every LazyKernel (:func:`_jit_all`)."""

    def __init__(self, fn, options: dict):
        self.py_func = fn
        self.options = options
        self.__name__ = fn.__name__
        self.__qualname__ = fn.__qualname__
        self.__module__ = fn.__module__
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn
        self._aot = _State.aot.get(f"{fn.__module__}:{fn.__name__}")
        self._jit = None

    def __call__(self, *args):
        if self._aot is not None:
            fn, n, checks, ndarray = self._aot
            if len(args) == n and all(type(a := args[i]) is ndarray and a.dtype == dt and a.ndim == nd
                                       and a.flags.c_contiguous and a.flags.aligned for i, dt, nd in checks):
                return fn(*args)
        if self._jit is None:  # arguments the exported signature does not take: numba specialises
            _jit_all()
        return self._jit(*args)

    def __getattr__(self, name):  # a dispatcher's attributes (signatures, ...): numba's own
        if name.startswith("__"):
            raise AttributeError(name)
        _jit_all()
        return getattr(self._jit, name)


def _np():
    import numpy

    return numpy


def _checks(codes) -> tuple:
    """(number of arguments, (index, dtype, ndim) of each array argument, ndarray) of an AOT_KERNELS entry."""
    np = _np()
    arrays = tuple((i, np.dtype(_ARG[c][1][0]), _ARG[c][1][1]) for i, c in enumerate(codes) if _ARG[c][1])
    return len(codes), arrays, np.ndarray


def _jit_all() -> None:
    """numba's dispatcher for every LazyKernel, put in its place in every loaded module of rig (a kernel
    compiled by numba finds its callees as dispatchers in its module's globals)."""
    _State.jitted = True
    preload_cython_blas()
    from numba import njit

    for k in _State.lazies:
        if k._jit is None:
            k._jit = njit(cache=True, **k.options)(k.py_func)
    for name, mod in list(sys.modules.items()):
        if (name == "rig" or name.startswith("rig.")) and mod is not None:
            d = vars(mod)
            for key, val in list(d.items()):
                if isinstance(val, LazyKernel):
                    d[key] = val._jit


def aot_dir() -> Path:
    """Where the built module lives: ``$RIG_AOT_DIR``, else ``rig/__pycache__`` beside numba's cache when it
    is writable, else ``$XDG_CACHE_HOME/rig`` (``~/.cache/rig``)."""
    env = os.environ.get("RIG_AOT_DIR")
    if env:
        return Path(env)
    here = _RIG / "__pycache__"
    if os.access(here if here.is_dir() else _RIG, os.W_OK):
        return here
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rig"


def _version_file(package: str, rel: str) -> bytes:
    spec = importlib.util.find_spec(package)  # no import: only where it is
    if spec is None or not spec.submodule_search_locations:
        return b""
    try:
        return (Path(spec.submodule_search_locations[0]) / rel).read_bytes()
    except OSError:
        return b""


def aot_key() -> str:
    """16 hex digits of the sources of every kernel under ``AOT_SOURCES``, the entries and their signatures,
    numba's and numpy's versions, this interpreter and machine: a change of any makes the module stale."""
    h = hashlib.sha256()
    h.update(repr((sys.implementation.cache_tag, platform.machine(), AOT_KERNELS)).encode())
    h.update(_version_file("numba", "_version.py"))
    h.update(_version_file("numpy", "version.py"))
    for rel in AOT_SOURCES:
        p = _RIG / rel
        for f in sorted(p.glob("*.py")) if p.is_dir() else [p]:
            h.update(str(f.relative_to(_RIG)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _module_name(key: str) -> str:
    return f"rig_kernels_{key}"


def aot_path(key: str | None = None) -> Path:
    """The built module's file for ``key`` (default: the current sources')."""
    return aot_dir() / (_module_name(key or aot_key()) + importlib.machinery.EXTENSION_SUFFIXES[0])


def load_aot(key: str | None = None):
    """The built module for ``key`` (default: the current sources'), imported from its file (OSError or
    ImportError when it is not there or does not load)."""
    key = key or aot_key()
    path = aot_path(key)
    if not path.is_file():
        raise FileNotFoundError(path)
    spec = importlib.util.spec_from_file_location(_module_name(key), path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def prefer_aot() -> str | None:
    """Use the ahead-of-time kernels in this process, when built from the current sources: call before the
    kernels' modules are imported. Returns None when they are used, else why not (``RIG_AOT=0``, numba
    already imported, not built yet, a failed build: the JIT kernels are used)."""
    if os.environ.get("RIG_AOT", "1") == "0":
        return "RIG_AOT=0"
    if "numba" in sys.modules:  # nothing to gain (a test session, a script): its kernels stay numba's
        return "numba is loaded"
    try:
        key = aot_key()
        if not aot_path(key).is_file():
            failed = _failed_path(key)
            return f"its build failed (see {failed})" if failed.is_file() else "not built yet"
        mod = load_aot(key)
    except (ImportError, OSError) as exc:
        return f"cannot load it ({exc})"
    _State.aot = {f"{m}:{n}": (getattr(mod, aot_symbol(m, n)),) + _checks(codes)
                  for m, n, _, codes in AOT_KERNELS if hasattr(mod, aot_symbol(m, n))}
    _State.lazy = True
    return None


def build_aot(out_dir: Path | None = None) -> Path:
    """Compile ``AOT_KERNELS`` with numba.pycc (a C compiler is needed) into the module :func:`prefer_aot`
    loads: the same Python functions as the JIT kernels, without the GIL as the JIT entries (the writer's
    thread encodes beside the simulation). Writes beside, then renames: a half-built module is never seen.
    Returns its path."""
    import tempfile
    import warnings

    with warnings.catch_warnings():  # pycc is "pending deprecation" since numba 0.57; nothing replaces it yet
        warnings.simplefilter("ignore")
        from numba.pycc import CC
        import numba.pycc.compiler as pycc_compiler

    out_dir = Path(out_dir) if out_dir is not None else aot_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    key = aot_key()
    name = _module_name(key)
    (out_dir / f"{name}.failed").unlink(missing_ok=True)

    class _NoGilFlags(pycc_compiler.Flags):  # pycc's wrapper keeps the GIL unless its flags say otherwise
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self.release_gil = True

    cc = CC(name)
    cc.verbose = False
    for module, fn_name, ret, codes in AOT_KERNELS:
        fn = getattr(importlib.import_module(module), fn_name)
        cc.export(aot_symbol(module, fn_name), aot_signature(ret, codes))(getattr(fn, "py_func", fn))
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        cc.output_dir = tmp
        flags, pycc_compiler.Flags = pycc_compiler.Flags, _NoGilFlags
        try:
            cc.compile()
        finally:
            pycc_compiler.Flags = flags
        built = Path(tmp) / (name + importlib.machinery.EXTENSION_SUFFIXES[0])
        target = out_dir / built.name
        os.replace(built, target)
    if aot_key() != key:
        target.unlink()
        raise RuntimeError("the kernels' sources changed during the build")
    for old in out_dir.glob("rig_kernels_*"):  # earlier sources' modules (a process that loaded one keeps it)
        if not old.name.startswith(name):
            old.unlink(missing_ok=True)
    return target


def _failed_path(key: str) -> Path:
    return aot_dir() / f"{_module_name(key)}.failed"


#: a build's lock older than this is taken for a build that died (a build takes a minute or two)
AOT_LOCK_STALE_S = 900.0


def _holder_gone(lock: Path) -> bool:
    """The process a lock names (its build) has ended."""
    try:
        os.kill(int(lock.read_text().strip()), 0)
    except ProcessLookupError:
        return True
    except (OSError, ValueError):  # alive but not ours, being written, unreadable: not gone
        return False
    return False


def _take_lock(lock: Path) -> bool:
    """Create ``lock`` atomically (``O_EXCL``: of two processes starting at once, one gets it); a lock older
    than ``AOT_LOCK_STALE_S`` or whose build has ended (a killed build) is removed first. True when this
    process holds it."""
    import time

    try:
        if time.time() - lock.stat().st_mtime >= AOT_LOCK_STALE_S or _holder_gone(lock):
            lock.unlink(missing_ok=True)
    except FileNotFoundError:
        pass
    try:
        fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as fh:
        fh.write(str(os.getpid()))
    return True


def build_aot_once(poll_s: float = 0.5) -> Path:
    """The module for the current sources, built here unless it is there; while another process builds it
    (a `rig run --sim`'s background build holds the lock), wait for that one instead of building it twice
    (until its lock goes or is stale), then build only if it did not."""
    import time

    key = aot_key()
    lock = aot_dir() / f"{_module_name(key)}.lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    while not aot_path(key).is_file():
        if _take_lock(lock):
            try:
                return build_aot()
            finally:
                lock.unlink(missing_ok=True)
        time.sleep(poll_s)
    return aot_path(key)


def start_aot_build() -> bool:
    """Start :func:`build_aot` in a detached process at low priority (``nice 10``), unless one is building
    for these sources (it holds their lock, :func:`_take_lock`) or their build failed. True when started."""
    import subprocess

    key = aot_key()
    lock = aot_dir() / f"{_module_name(key)}.lock"
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        if _failed_path(key).exists() or not _take_lock(lock):
            return False
    except OSError:
        return False
    try:
        p = subprocess.Popen([sys.executable, "-c", f"from rig.jitstart import _build_main; _build_main({key!r})"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
        lock.write_text(str(p.pid))  # the build's own: this process ends first
    except OSError:
        lock.unlink(missing_ok=True)
        return False
    return True


def _build_main(key: str) -> None:
    """The detached build of :func:`start_aot_build`: a failure is written beside the module (``.failed``, its
    traceback), so that later runs say so instead of building again (``rig warmup`` retries)."""
    import traceback

    os.nice(10)
    try:
        build_aot()
    except BaseException:  # noqa: BLE001 - any failure: written down, the JIT kernels stay in use
        if aot_key() == key:
            _failed_path(key).write_text(traceback.format_exc())
    finally:
        (aot_dir() / f"{_module_name(key)}.lock").unlink(missing_ok=True)
