"""How the nodes spin: a lean wait-set loop over the per-step subscriptions (rclpy imported on use).

An rclpy executor's ``spin_once`` runs one callback per call: the EventsExecutor wakes the node
once per message, the SingleThreadedExecutor also rebuilds its wait set from every entity of the
node each time. ``lean`` instead waits once on every subscription of the node (a
step's measurements, wrenches, acknowledgements, and ``/clock``) and takes every message then
ready (CDR bytes for the raw per-step ones), so a burst of one step's messages costs one
wake-up (benchmarks/msg_cost_bench.py measures the three). The same wait covers the node's
timers and services (parameters, the graph watch); when one is ready, a SingleThreadedExecutor
runs it. That executor honours callback groups, so the subscriptions are moved into a group it
never runs (the EventsExecutor ignores groups and cannot be the side executor).

:data:`FASTDDS_PROFILE` is the Fast DDS profile every non-secure process of a run loads
(``FASTRTPS_DEFAULT_PROFILES_FILE``, set by the launcher): writers without positive
acknowledgements (the file says why).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: the project's Fast DDS profile of non-secure runs
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")
#: the ways a node can spin (``--executor`` / the ``executor`` parameter)
EXECUTORS = ("events", "lean", "single")
#: ``lean``: wall seconds between two turns of the side executor when no timer or service is ready
SIDE_PERIOD = 1.0


def _hot_group() -> Any:
    """A callback group no executor runs: its subscriptions are taken by a :class:`HotLoop`."""
    from rclpy.callback_groups import CallbackGroup

    class HotGroup(CallbackGroup):
        def can_execute(self, entity: Any) -> bool:
            return False

        def beginning_execution(self, entity: Any) -> bool:
            return False

        def ending_execution(self, entity: Any) -> None:
            return None

    return HotGroup()


def check_kind(kind: str) -> None:
    if kind not in EXECUTORS:
        raise ValueError(f"executor {kind!r} is not one of {', '.join(EXECUTORS)}")


def make_executor(kind: str, context: Any) -> Any:
    """The rclpy executor of ``kind`` (``lean``: the side executor, a SingleThreadedExecutor)."""
    check_kind(kind)
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    from rclpy.executors import SingleThreadedExecutor

    return SingleThreadedExecutor(context=context)


class HotLoop:
    """Wait on ``subscriptions``, ``timers`` and ``services``; call each subscription's callback with
    every message taken (CDR bytes for a raw subscription, else the message). Timers and services
    are only waited on: :meth:`spin_once` says when one is ready, for an executor to run it."""

    def __init__(
        self, context: Any, subscriptions: Sequence[Any], timers: Sequence[Any] = (), services: Sequence[Any] = ()
    ) -> None:
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        self._rcl_error = _rclpy.RCLError
        self._context = context
        self._wait_set = _rclpy.WaitSet(len(subscriptions), 0, len(timers), 0, len(services), 0, context.handle)
        self._entries = [(s.handle, s.msg_type, s.raw, s.callback) for s in subscriptions]
        self._timers = [t.handle for t in timers]
        self._services = [s.handle for s in services]

    def spin_once(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` (wall s); handle every message then ready; True if a timer or a
        service is ready too."""
        ws = self._wait_set
        ws.clear_entities()
        for entry in self._entries:
            ws.add_subscription(entry[0])
        for handle in self._timers:
            ws.add_timer(handle)
        for handle in self._services:
            ws.add_service(handle)
        try:
            ws.wait(max(0, int(timeout_s * 1e9)))
        except self._rcl_error:
            if not self._context.ok():
                return False  # shut down while waiting (SIGINT/SIGTERM)
            raise
        ready = ws.get_ready_entities("subscription")
        for handle, msg_type, raw, callback in self._entries:
            if handle.pointer in ready:
                taken = handle.take_message(msg_type, raw)
                while taken is not None:
                    callback(taken[0])
                    taken = handle.take_message(msg_type, raw)
        return bool(self._timers and ws.get_ready_entities("timer")) or bool(
            self._services and ws.get_ready_entities("service")
        )


class Spinner:
    """Spins ``node`` with executor ``kind``.

    ``lean``: a :class:`HotLoop` over every subscription, timer and service the node has when the
    spinner is made (subscriptions moved into a callback group no executor runs); a
    SingleThreadedExecutor runs a ready timer or service, and anything else of the node (QoS
    events) every :data:`SIDE_PERIOD`. ``events`` / ``single``: that executor's ``spin_once``.
    """

    def __init__(self, kind: str, node: Any) -> None:
        self.executor = make_executor(kind, node.context)
        self.executor.add_node(node)
        self.hot = None
        if kind == "lean":
            hot = list(node.subscriptions)
            group = _hot_group()
            for sub in hot:
                sub.callback_group = group
            self.hot = HotLoop(node.context, hot, list(node.timers), list(node.services))
        self._next_side = 0.0

    def spin_once(self, timeout_sec: float) -> None:
        """Handle what arrives within ``timeout_sec`` wall seconds (lean: every message then ready)."""
        if self.hot is None:
            self.executor.spin_once(timeout_sec=max(timeout_sec, 0.0))
            return
        side = self.hot.spin_once(timeout_sec)
        now = time.monotonic()
        if side or now >= self._next_side:
            self._next_side = now + SIDE_PERIOD
            self.executor.spin_once(timeout_sec=0.0)
