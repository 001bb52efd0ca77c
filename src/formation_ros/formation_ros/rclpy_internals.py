"""rclpy beyond its public API, in one place (written against the pinned ros-rclpy 7.1.6;
tests/test_library_internals.py checks every name below against the installed rclpy
and names what changed).

- :data:`RCLError`: the exception of rclpy's C extension, which rclpy gives no public name (a wait
  interrupted at shutdown, a graph query or a publish after the context ended).
- :class:`SubscriptionWaitSet` and :func:`raw_taker`: a wait set of subscriptions and
  ``take_message(raw=True)``, the recorder's loop without an executor (an executor's callback costs
  tens of µs per message; formation_bag.record_node).
- :func:`now_ns_reader`: the clock's time [ns] through its handle, ~0.7 µs against ~3 µs for
  ``Clock.now()`` (which builds a Time object): the agent reads it for every message it checks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

RCLError: type[Exception] = _rclpy.RCLError

#: what this module uses, for the test: (owner, attribute)
INTERNALS = (
    ("rclpy.impl.implementation_singleton.rclpy_implementation", "RCLError"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation", "WaitSet"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.WaitSet", "clear_entities"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.WaitSet", "add_subscription"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.WaitSet", "wait"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.WaitSet", "get_ready_entities"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.Subscription", "take_message"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.Subscription", "pointer"),
    ("rclpy.impl.implementation_singleton.rclpy_implementation.Clock", "get_now"),
    ("rclpy.subscription.Subscription", "handle"),
    ("rclpy.clock.Clock", "handle"),
    ("rclpy.context.Context", "handle"),
)


class SubscriptionWaitSet:
    """A wait set of ``capacity`` subscriptions of ``context`` (rclpy Subscription objects)."""

    def __init__(self, capacity: int, context: Any) -> None:
        self._wait_set = _rclpy.WaitSet(capacity, 0, 0, 0, 0, 0, context.handle)

    def wait(self, subscriptions: Iterable[Any], timeout_ns: int) -> list[int]:
        """Wait up to ``timeout_ns`` for any of ``subscriptions``; the :func:`pointer` of each that has data.
        Raises :data:`RCLError` when the wait is interrupted (the context shut down)."""
        ws = self._wait_set
        ws.clear_entities()
        for sub in subscriptions:
            ws.add_subscription(sub.handle)
        ws.wait(timeout_ns)
        return list(ws.get_ready_entities("subscription"))


def pointer(subscription: Any) -> int:
    """The identity of a subscription in :meth:`SubscriptionWaitSet.wait`'s answer."""
    return int(subscription.handle.pointer)


def raw_taker(subscription: Any) -> Callable[[Any, bool], Any]:
    """``take(msg_class, True)``: the next message's (serialized bytes, info), or None when none is queued."""
    return subscription.handle.take_message


def now_ns_reader(clock: Any) -> Callable[[], int]:
    """A function returning ``clock``'s time [ns] (for a ROS time clock, the latest /clock)."""
    handle = clock.handle
    return lambda: int(handle.get_now().nanoseconds)
