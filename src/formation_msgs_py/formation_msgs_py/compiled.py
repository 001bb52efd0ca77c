"""The one switch between the compiled (numba) and the interpreted form of the numerical kernels.

The controller, the SO(3) maps, the funnels, the plant and the closed-loop stepping are written
once, as plain Python on floats and small numpy arrays, and compiled with :func:`kernel`
(``numba.njit``, cached on disk so that a second process loads the machine code instead of
compiling it); the small formulas they share are :func:`formula` (compiled into their callers).
``NUMBA_DISABLE_JIT=1`` runs every kernel as the Python it is written in; each compiled kernel
also keeps that Python as ``.py_func``.

``error_model="numpy"``: a division by zero gives inf/NaN as in numpy instead of raising; the
callers check finiteness where the paper's law can leave its domain.

``_nrt=False``: the kernels run without numba's reference-counting runtime. They cannot allocate
(an ``np.empty``, a ``.copy()`` or a slice assignment does not compile: callers preallocate and
kernels write element by element), and no array they pass on costs an atomic increment and
decrement per call: with the runtime, those were most of a control step's time.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)

#: True when ``NUMBA_DISABLE_JIT`` is set (not "0"): every kernel is its own Python source, and
#: numba is not even imported (an agent process saves its start time and memory).
INTERPRETED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")


#: formulas declared before numba was imported, registered at the first :func:`kernel`
_PENDING: list[Callable] = []


def formula(fn: F) -> F:
    """A small formula on floats and tuples (an SO(3) product, a funnel): plain Python when called
    from Python (where numpy arrays work elementwise), compiled into every kernel that calls it.

    Declaring it does not import numba (``formation_msgs_py.spec`` uses funnels and SO(3) maps
    and is imported by every command); :func:`kernel` registers it before any kernel compiles.
    """
    if not INTERPRETED:
        _PENDING.append(fn)
        if _numba is not None:
            _register_pending()
    return fn


def kernel(fn: F) -> F:
    """Compile ``fn`` in nopython mode, cached next to its source (or in numba's user cache)."""
    if INTERPRETED:
        return fn
    global _numba
    import numba

    _numba = numba
    _register_pending()
    return numba.njit(cache=True, error_model="numpy", _nrt=False)(fn)


_numba = None


def _register_pending() -> None:
    from numba.extending import register_jitable

    while _PENDING:
        register_jitable(error_model="numpy", _nrt=False)(_PENDING.pop())
