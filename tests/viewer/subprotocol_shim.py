"""Test-only: lets Foxglove Studio 1.48 reach the live view. Studio 1.x offers only the WebSocket
subprotocol ``foxglove.websocket.v1``; the live view (foxglove-sdk) speaks the same protocol under its
newer name ``foxglove.sdk.v1`` and refuses the old one. This relay on 127.0.0.1 accepts the old name
and forwards every frame, unchanged, to the server under the new one."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.typing import Subprotocol

OLD, NEW = Subprotocol("foxglove.websocket.v1"), Subprotocol("foxglove.sdk.v1")


async def _pump(source, sink) -> None:  # type: ignore[no-untyped-def]
    try:
        async for frame in source:
            await sink.send(frame)  # text stays text, binary stays binary
    except ConnectionClosed:
        pass
    finally:
        await sink.close()


@contextmanager
def renaming(upstream: str) -> Iterator[str]:
    """Relay ``foxglove.websocket.v1`` clients to the live view at ``upstream`` (ws://HOST:PORT); yields the
    relay's own URL (a free port of 127.0.0.1)."""
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    stop = asyncio.Event()
    url: list[str] = []

    async def relay(client: ServerConnection) -> None:
        async with connect(upstream, subprotocols=[NEW], max_size=None) as server:
            await asyncio.gather(_pump(client, server), _pump(server, client))

    async def main() -> None:
        async with serve(relay, "127.0.0.1", 0, subprotocols=[OLD], max_size=None) as server:
            port = next(iter(server.sockets)).getsockname()[1]
            url.append(f"ws://127.0.0.1:{port}")
            ready.set()
            await stop.wait()

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), name="subprotocol-shim", daemon=True)
    thread.start()
    if not ready.wait(timeout=30):
        raise RuntimeError("the subprotocol relay did not start")
    try:
        yield url[0]
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(timeout=10)
