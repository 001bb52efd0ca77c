"""The ROS-free core of formation: what every other package agrees on, with no ROS import.

:mod:`spec` (a formation file read and validated), :mod:`formation` (the typed formation and the
agent's and the simulator's views of it), :mod:`schema` (its fields), :mod:`loader` (YAML with line
and column), :mod:`options` (the runners' options), :mod:`verdict` (PASS/FAIL/INCOMPLETE and exit
statuses), :mod:`faults`, :mod:`errors`, :mod:`so3` and :mod:`rotations` (SO(3) maps),
:mod:`funnels` (performance functions) and :mod:`numba_kernels` (the one switch between compiled
and interpreted kernels, and numba's cache).
"""

from formation_core.errors import FormationError, FormationSpecError

__all__ = ["FormationError", "FormationSpecError"]
