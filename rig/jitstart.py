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

import importlib.machinery
import importlib.util
import sys
from pathlib import Path

_NAMES = ("cython_blas", "cython_lapack")


def preload_cython_blas() -> bool:
    """Load ``scipy.linalg.cython_blas`` / ``cython_lapack`` without ``scipy.linalg`` (see the module
    docstring). Returns True when both are in ``sys.modules`` afterwards."""
    full = [f"scipy.linalg.{n}" for n in _NAMES]
    if all(n in sys.modules for n in full):
        return True
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
