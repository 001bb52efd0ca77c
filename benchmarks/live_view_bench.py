"""CPU of the live view (--foxglove) per display instant: what a lockstep step pays for it.

    .venv/bin/python benchmarks/live_view_bench.py [FORMATION ...]

At a display instant the simulator hands the live view the markers and funnels it has just
published and a /clock (formation_sim.node.display): three LiveView.send calls, each a copy into
the server's queue and, for the first of an instant, the broadcast of the time. Measured with no
client and with one client subscribed to every channel (a thread reading the WebSocket as a
viewer does). CPU time of this thread (``time.thread_time``: the server's own threads and the
client are not counted, as they are not the step's), per instant, after a warm-up. Results in
BENCHMARKS.md.
"""

from __future__ import annotations

import asyncio
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import websockets

from formation_bag.foxglove_server import SUBPROTOCOL, LiveView, display_topics
from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.codec import clock_bytes
from formation_sim.core.simulation import Simulation
from formation_sim.node.display import FUNNEL_FIELDS
from formation_sim.views.display_wire import FunnelsWire, MarkerArrayWire
from formation_sim.views.markers import FormationScene

REPO = Path(__file__).resolve().parents[1]
DEFAULT = ("paper_5agents.yaml", "realtime_20agents_100hz.yaml")
REPEAT = 3000


def _client(url: str, stop: threading.Event, subscribed: threading.Event, counter: list[int]) -> None:
    async def run() -> None:
        async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:  # type: ignore[list-item]
            channels: list[int] = []
            while len(channels) < len(display_topics()):
                msg = json.loads(await ws.recv())
                if msg.get("op") == "advertise":
                    channels += [c["id"] for c in msg["channels"]]
            subs = [{"id": i + 1, "channelId": c} for i, c in enumerate(channels)]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            subscribed.set()
            while not stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return  # the server stopped
                counter[0] += isinstance(frame, bytes) and frame[0] == 1  # messageData (2: time)

    asyncio.run(run())


def instant_cost(path: Path, with_client: bool) -> tuple[float, int, int]:
    """(CPU s per display instant, markers bytes, frames the client received)."""
    spec = load_formation(path)
    state = Simulation(simulator_view(spec)).state
    scene = FormationScene(spec)
    u = np.random.default_rng(0).normal(size=(len(spec.agents), 6))
    f = scene.frame(0.7, state.p, state.R, u)
    markers = MarkerArrayWire(scene, topics.WORLD_FRAME).encode(700_000_000, f)
    funnels = FunnelsWire([e.name for e in spec.edges], FUNNEL_FIELDS).encode(
        np.stack([f.funnels[name] for name in FUNNEL_FIELDS], axis=1)
    )
    live = LiveView("127.0.0.1:0", name="bench")
    live.open(display_topics())
    stop, subscribed, counter = threading.Event(), threading.Event(), [0]
    reader = None
    if with_client:
        reader = threading.Thread(target=_client, args=(live.url, stop, subscribed, counter), daemon=True)
        reader.start()
        subscribed.wait(30)
        time.sleep(0.5)  # the server takes the subscription
    m_topic, f_topic = "/" + topics.MARKERS, "/" + topics.FUNNELS

    def instant(ns: int) -> None:
        live.send(m_topic, markers, ns)
        live.send(f_topic, funnels, ns)
        live.send(topics.CLOCK, clock_bytes(ns), ns)

    for k in range(100):
        instant(k)
    t0 = time.thread_time()
    for k in range(100, 100 + REPEAT):
        instant(k * 33_333_333)
        if with_client and k % 100 == 0:
            time.sleep(0.01)  # paced a little, as instants are: the client keeps up (no dropped backlog)
    cost = (time.thread_time() - t0) / REPEAT
    time.sleep(1.0)
    stop.set()
    if reader is not None:
        reader.join(5)  # the client leaves before the server stops
    live.close()
    return cost, len(markers), counter[0]


def main(argv: list[str]) -> None:
    for name in argv or DEFAULT:
        path = Path(name) if Path(name).exists() else REPO / "config" / name
        none, size, _ = instant_cost(path, with_client=False)
        one, _, received = instant_cost(path, with_client=True)
        print(
            f"{path.name}: markers {size} B; per display instant {none * 1e6:.1f} µs with no client, "
            f"{one * 1e6:.1f} µs with one subscribed client ({received} frames received of {3 * (REPEAT + 100)})"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
