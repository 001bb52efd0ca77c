"""The live view: display topics served over the Foxglove WebSocket protocol, without ROS.

``--foxglove [HOST:]PORT`` on formation-sim, formation-launch and formation-replay starts a
`foxglove-sdk <https://pypi.org/project/foxglove-sdk/>`_ WebSocket server (bound to 127.0.0.1
unless a host is given) with one channel per display topic: encoding ``cdr``, schema the ROS 2
message definition (``ros2msg``, from rosbags' Jazzy typestore). A message is served as the CDR
bytes the node publishes anyway (the display's templates, the bag's records): nothing is
serialized again, so a send costs a lockstep step one copy into the server's queue (the server's
own thread writes it to the sockets). Its log time is the message's simulation time [integer ns];
the server also broadcasts that time (the protocol's ``time`` capability), so a viewer's clock
follows the simulation.

The server speaks the subprotocol ``foxglove.sdk.v1`` only (docs/ros2.md, "Live view").
"""

from __future__ import annotations

import math
import socket
from collections.abc import Mapping
from typing import Any

from formation_bag.writer import typestore
from formation_core.options import split_endpoint
from formation_msgs_py import topics

#: the subprotocol the server accepts (foxglove-sdk 0.30; ``foxglove.websocket.v1`` is refused)
SUBPROTOCOL = "foxglove.sdk.v1"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
CLOCK = "rosgraph_msgs/msg/Clock"
#: the throttle of formation-replay's live view [Hz of bag time]: the simulator's default display rate
DEFAULT_RATE = 30.0


class LiveViewError(Exception):
    """The live view could not start (port taken, address not available, foxglove-sdk missing)."""


def endpoint_problem(endpoint: str) -> str | None:
    """Why the live view could not listen on ``endpoint`` ([HOST:]PORT), or None: a launcher's check
    before it starts anything (the simulator binds the port itself later)."""
    host, port = split_endpoint(endpoint)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        with socket.socket(infos[0][0], socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server's listener does
            probe.bind(infos[0][4])
    except OSError as exc:
        return f"--foxglove {endpoint}: cannot listen on {host}:{port}: {exc.strerror or exc}"
    return None


def message_definition(msgtype: str) -> str:
    """The ROS 2 ``.msg`` definition of ``msgtype`` (e.g. ``visualization_msgs/msg/MarkerArray``)
    with its dependencies, as ``ros2msg`` schemas carry it (rosbags' Jazzy typestore)."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


def display_topics(
    markers: str = "/" + topics.MARKERS, funnels: str = "/" + topics.FUNNELS, links: str | None = None
) -> dict[str, str]:
    """The live view's topics and their ROS 2 types: markers, funnels, the link ages with a link
    model (names as resolved by the node), ``/diagnostics`` and ``/clock``."""
    out = {markers: MARKER_ARRAY, funnels: FLOAT64_MULTI_ARRAY}
    if links is not None:
        out[links] = FLOAT64_MULTI_ARRAY
    out.update({topics.DIAGNOSTICS: DIAGNOSTIC_ARRAY, topics.CLOCK: CLOCK})
    return out


class LiveView:
    """A Foxglove WebSocket server on ``endpoint`` ([HOST:]PORT); :meth:`open` adds its channels.

    ``rate`` [Hz of log time] throttles each topic to one message per 1/rate s (on the grid
    k/rate, as the display publishes), except ``/diagnostics`` (each agent's comes at most every
    ``diagnostics_period`` wall seconds; one topic for all); None: every message is sent (the
    caller publishes at the display rate already).
    """

    def __init__(self, endpoint: str, *, name: str, rate: float | None = None) -> None:
        try:
            from foxglove.websocket import Capability

            import foxglove
        except ImportError as exc:  # pinned in ros2_ws/requirements.txt; absent in a bare ROS install
            raise LiveViewError(f"--foxglove needs the Python package foxglove-sdk ({exc})") from None
        host, port = split_endpoint(endpoint)
        self.context = foxglove.Context()  # its own: nothing else logged through the SDK reaches it
        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, capabilities=[Capability.Time], context=self.context
            )
        except Exception as exc:  # the SDK raises a RuntimeError subclass of its own (bind failures)
            raise LiveViewError(f"--foxglove {endpoint}: could not serve on {host}:{port}: {exc}") from None
        self.host = host
        self.port = self.server.port
        self.rate = rate
        self.channels: dict[str, Any] = {}
        self.next_ns: dict[str, int] = {}
        self.sent: dict[str, int] = {}
        self.time_ns = -1

    def open(self, topic_types: Mapping[str, str]) -> None:
        """One channel per topic: encoding ``cdr``, schema ``ros2msg`` of its type
        (``pkg/msg/Name``); a viewer sees them advertised at once."""
        import foxglove

        for topic, msgtype in topic_types.items():
            schema = foxglove.Schema(name=msgtype, encoding="ros2msg", data=message_definition(msgtype).encode())
            channel = foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self.context)
            self.channels[topic] = channel.base  # the native channel: log(bytes, ns) without type dispatch
            self.next_ns[topic] = -1
            self.sent[topic] = 0

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def send(self, topic: str, data: bytes, ns: int) -> bool:
        """Serve ``data`` (CDR bytes with their 4-byte header) on ``topic`` at log time ``ns``
        [integer ns]; False if the throttle dropped it."""
        if self.rate is not None and topic != topics.DIAGNOSTICS:
            if ns < self.next_ns[topic]:
                return False
            self.next_ns[topic] = round((math.floor(ns * self.rate / 1e9 + 1e-6) + 1.0) / self.rate * 1e9)
        self.channels[topic].log(data, ns)
        self.sent[topic] += 1
        if ns > self.time_ns:
            self.time_ns = ns
            self.server.broadcast_time(ns)
        return True

    def rewind(self) -> None:
        """Log time starts again (a replay's next loop): the throttle and the broadcast time restart."""
        self.next_ns = dict.fromkeys(self.next_ns, -1)
        self.time_ns = -1

    def close(self) -> None:
        """Stop the server (clients are disconnected)."""
        for channel in self.channels.values():
            channel.close()
        self.server.stop()
