"""The one switch between the compiled (numba) and the interpreted form of the numerical kernels.

The controller, the SO(3) maps, the funnels, the plant and the closed-loop stepping are written
once, as plain Python on floats, tuples and small numpy arrays. A :func:`kernel` is an entry point
called from Python: compiled per argument types (``numba.njit``) and cached on disk, so that a
second process loads the machine code instead of compiling it. A :func:`formula` is every other
function: compiled into the kernels that call it, typed by its arguments' types (never by their
literal values: a formula called with ``0`` and with ``i`` is compiled once), with no Python or C
entry of its own. ``NUMBA_DISABLE_JIT=1`` runs every kernel and formula as the Python it is
written in; each compiled kernel also keeps that Python as ``.py_func``.

A first run compiles every (function, argument types) it meets, each through numba's typing and
lowering and LLVM, so the code keeps that set small: formulas take 3-vectors as tuples and 3×3
matrices as row tuples (:func:`formation_msgs_py.so3.vec3` and :func:`formation_msgs_py.so3.matrix_rows`
read them from arrays), every call site of a kernel passes the same types (C-contiguous arrays),
and a kernel's own body calls formulas that no other formula calls (numba compiles a formula once
per kind of caller, kernel or formula: the SO(3) products and funnels are called from formulas only).

``error_model="numpy"``: a division by zero gives inf/NaN as in numpy instead of raising; the
callers check finiteness where the paper's law can leave its domain.

``_nrt=False``: the kernels run without numba's reference-counting runtime. They cannot allocate
(an ``np.empty``, a ``.copy()`` or a slice assignment does not compile: callers preallocate and
kernels write element by element), and no array they pass on costs an atomic increment and
decrement per call: with the runtime, those were most of a control step's time.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from types import ModuleType
from typing import TypeVar

F = TypeVar("F", bound=Callable)

#: True when ``NUMBA_DISABLE_JIT`` is set (not "0"): every kernel is its own Python source, and
#: numba is not even imported (an agent process saves its start time and memory).
INTERPRETED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")


#: formulas declared before numba was imported, registered at the first :func:`kernel`
_PENDING: list[Callable] = []


def formula(fn: F) -> F:
    """A function compiled into every kernel that calls it (an SO(3) product, a funnel, a step of
    the controller): plain Python when called from Python (where numpy arrays work elementwise).

    Declaring it does not import numba (``formation_msgs_py.spec`` uses funnels and SO(3) maps
    and is imported by every command); :func:`kernel` registers it before any kernel compiles.
    """
    if not INTERPRETED:
        _PENDING.append(fn)
        if _numba is not None:
            _register_pending()
    return fn


def kernel(fn: F) -> F:
    """Compile ``fn`` in nopython mode, cached next to its source (or in ``NUMBA_CACHE_DIR``).

    No C entry (``no_cfunc_wrapper``): kernels are called from Python or from other kernels, never
    as C function pointers, and the wrapper is LLVM work at every compilation.
    """
    if INTERPRETED:
        return fn
    numba = _import_numba()
    _register_pending()
    return numba.njit(cache=True, error_model="numpy", _nrt=False, no_cfunc_wrapper=True)(fn)


_numba = None

#: Modules numba imports that no kernel needs, together a few tenths of a second of every compiled
#: process's start: ``coverage`` (numba's coverage support, when coverage is installed and not
#: running), scipy (numba checks its version, and ``numba.np.arraymath`` imports scipy.linalg to
#: check for a BLAS that only its np.convolve/np.correlate would use; np.dot and np.linalg import it
#: when they compile) and cffi (numba's typing of cffi functions).
_NOT_NEEDED = ("coverage", "scipy", "cffi")


def _import_numba() -> ModuleType:
    """numba, and the modules of it that import :data:`_NOT_NEEDED` (else imported by its first cache
    load or compilation), imported while those are hidden; later importers find them as usual."""
    global _numba
    if _numba is None:
        hidden = [name for name in _NOT_NEEDED if name not in sys.modules]
        # None in sys.modules: ``import`` fails at once (the import system's documented blocker, which
        # typeshed's dict[str, ModuleType] does not express)
        sys.modules.update(dict.fromkeys(hidden))  # type: ignore[arg-type]
        try:
            import numba
            import numba.core.typing.cffi_utils
            import numba.np.arraymath
        finally:
            for name in hidden:
                sys.modules.pop(name, None)
        _numba = numba
    return _numba


def _register_pending() -> None:
    from numba.extending import register_jitable

    while _PENDING:
        register_jitable(error_model="numpy", _nrt=False, no_cfunc_wrapper=True)(_PENDING.pop())
