"""A minimal Foxglove WebSocket client for the live-view tests (the ``websockets`` package).

It speaks what a viewer does: offers a subprotocol, reads the server's ``advertise``, subscribes
to topics by channel id and reads ``messageData`` frames (opcode 1: uint32 subscription id,
uint64 log time [ns], then the message's bytes, little-endian).
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import websockets

MESSAGE_DATA = 0x01


@dataclass
class Received:
    """What a client saw: the advertised channels by topic, and the messages by topic (log time, bytes)."""

    channels: dict[str, dict] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)


async def _receive(
    url: str,
    wanted: Iterable[str],
    subprotocol: str,
    deadline: float,
    tick: Callable[[], None] | None,
) -> Received:
    wanted = set(wanted)
    got = Received()
    async with websockets.connect(url, subprotocols=[subprotocol], max_size=None) as ws:  # type: ignore[list-item]
        by_id: dict[int, str] = {}
        while not wanted <= set(got.channels):
            msg = json.loads(await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic())))
            if msg.get("op") == "advertise":
                for ch in msg["channels"]:
                    got.channels[ch["topic"]] = ch
        subscriptions = []
        for sub_id, topic in enumerate(sorted(wanted), start=1):
            by_id[sub_id] = topic
            subscriptions.append({"id": sub_id, "channelId": got.channels[topic]["id"]})
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        while not all(got.messages.get(t) for t in wanted):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no message on {sorted(wanted - set(got.messages))} from {url}")
            if tick is not None:
                tick()  # the test's server sends now (a message sent before the subscription is not delivered)
            try:
                frame = await asyncio.wait_for(ws.recv(), 0.2 if tick is not None else 1.0)
            except TimeoutError:
                continue
            if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                got.messages.setdefault(by_id[sub_id], []).append((log_time, frame[13:]))
    return got


def receive(
    url: str,
    topics: Iterable[str],
    *,
    subprotocol: str = "foxglove.sdk.v1",
    timeout: float = 60.0,
    tick: Callable[[], None] | None = None,
) -> Received:
    """Connect to ``url``, subscribe to ``topics`` and return once each has a message (TimeoutError
    after ``timeout`` s); ``tick`` is called while waiting (a test that serves the messages itself)."""
    return asyncio.run(_receive(url, topics, subprotocol, time.monotonic() + timeout, tick))


def wait_and_receive(url: str, topics: Iterable[str], alive: Callable[[], bool], timeout: float) -> Received:
    """:func:`receive`, connecting again until the server listens (while ``alive()``), within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return receive(url, topics, timeout=max(1.0, deadline - time.monotonic()))
        except OSError:  # not listening yet
            if not alive() or time.monotonic() > deadline:
                raise
            time.sleep(0.2)
