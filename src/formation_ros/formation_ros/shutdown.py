"""How a node process (the simulator, an agent) stops on SIGINT or SIGTERM.

rclpy's signal handlers (installed by ``rclpy.init``) shut the context down on SIGINT and SIGTERM
and wake the EventsExecutor; on SIGINT they then call Python's handler, whose default raises
KeyboardInterrupt wherever the main thread is, most often inside an executor callback: rclpy logs
it as ``[FATAL] Exception in 'timers' callback`` before it unwinds through the executor.
:func:`init` makes SIGINT mean what SIGTERM means: the context shuts down and the node's loop,
which checks it, ends; nothing is raised.

A stopped node process then leaves with :func:`exit_now`. Interpreter finalization (freeing
numba, llvmlite, scipy and rclpy module by module, then Fast DDS's exit handlers) costs
0.1–0.4 s of CPU per process and does nothing a run needs once the node is destroyed (its Fast
DDS participant and /dev/shm segment gone) and the outputs are closed. With the six processes of
a run stopping at once on a loaded 2-core machine it took 1.3–2.5 s, past the launcher's grace:
SIGKILL, and the participant's /dev/shm segment was left behind whenever the node's executor
(which keeps the participant until it is shut down, see agent_node.AgentNode.spin) had not been
collected yet.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:
    from rclpy.context import Context

_signalled: list[int] = []


def _note(signum: int, _frame: Any) -> None:
    """Python's part of SIGINT (rclpy's handler shuts the context down, in a thread of its own)."""
    _signalled.append(signum)


def init(args: Sequence[str]) -> None:
    """``rclpy.init(args=args)`` with SIGINT stopping as SIGTERM does (no KeyboardInterrupt).

    Our handler goes in first: rclpy's keeps it as the one to chain to. A SIGINT that came before
    rclpy's handler was in place raises KeyboardInterrupt here (nothing is started yet).
    """
    import rclpy

    signal.signal(signal.SIGINT, _note)
    rclpy.init(args=list(args))
    if _signalled:
        raise KeyboardInterrupt


def exit_now(code: int, context: Context) -> NoReturn:
    """End the process with ``code`` without interpreter finalization: only once every node this
    process created in ``context`` is destroyed (and its executor shut down before) and every
    output it writes is closed. rclpy's log files (ROS_LOG_DIR) are closed here: rclpy closes them
    only when it shuts ``context`` down itself, not after its signal handler did (Context's
    idempotent ``_logging_fini``, under its lock as rclpy calls it)."""
    try:
        with context._lock:
            context._logging_fini()
    except AttributeError:  # an rclpy other than Jazzy's 7.1: its log files may end unflushed, the run does not
        pass
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
