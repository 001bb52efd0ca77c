"""The one switch between the compiled (numba) and the interpreted form of the numerical kernels.

The controller, the SO(3) maps, the funnels, the plant and the closed-loop stepping are written
once, as plain Python on floats and small numpy arrays, and compiled with :func:`kernel`
(``numba.njit``, cached on disk so that a second process loads the machine code instead of
compiling it). ``NUMBA_DISABLE_JIT=1`` runs every kernel as the Python it is written in; each
compiled kernel also keeps that Python as ``.py_func``.

``error_model="numpy"``: a division by zero gives inf/NaN as in numpy instead of raising; the
callers check finiteness where the paper's law can leave its domain.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)

#: True when ``NUMBA_DISABLE_JIT`` is set (not "0"): every kernel is its own Python source, and
#: numba is not even imported (an agent process saves its start time and memory).
INTERPRETED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")


def kernel(fn: F) -> F:
    """Compile ``fn`` in nopython mode, cached next to its source (or in numba's user cache)."""
    if INTERPRETED:
        return fn
    import numba

    return numba.njit(cache=True, error_model="numpy")(fn)
