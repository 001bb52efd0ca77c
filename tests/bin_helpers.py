"""Where the tests find the project's console scripts (formation-launch, formation-agent, ...).

The tests run against whatever install the interpreter running them belongs to, so that the same
tests check the project's venv, a colcon install space or any other install. For each name, the
first of:

1. ``$FORMATION_BIN``: a directory, or several separated by ``os.pathsep``, searched in order;
2. the directory of this interpreter (``.venv/bin`` when ``.venv/bin/python -m pytest`` or
   ``./ros2_ws/test.sh`` runs the tests, whatever PATH holds);
3. a sourced colcon/ament install space: ``<prefix>/lib/<package>/NAME`` for each prefix of
   ``AMENT_PREFIX_PATH`` (where ``colcon build`` installs the scripts and ``ros2 run`` finds them);
4. PATH;
5. the repository's ``.venv/bin`` (the path a missing script is reported at).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = REPO / ".venv" / "bin"


def executable(name: str) -> str:
    """The path of console script ``name`` (see the module's order); the ``.venv/bin`` path when
    no install holds it, so that a missing script fails where it is started, naming that path."""
    forced = os.environ.get("FORMATION_BIN")
    if forced:
        for directory in filter(None, forced.split(os.pathsep)):
            if (Path(directory) / name).is_file():
                return str(Path(directory) / name)
        return str(Path(forced.split(os.pathsep)[0]) / name)
    here = Path(sys.executable).parent / name
    if here.is_file():
        return str(here)
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        found = sorted(Path(prefix).glob(f"lib/*/{name}"))
        if found:
            return str(found[0])
    return shutil.which(name) or str(VENV_BIN / name)


def executable_dir(name: str = "formation-launch") -> Path:
    """The directory of console script ``name`` (for a PATH entry of a child's environment)."""
    return Path(executable(name)).parent
