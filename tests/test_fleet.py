"""A fleet against a real clustered broker: ten gateways, each on a simulated line,
publish to a 3-node NATS cluster (JetStream, the MQTT listener on every node), each
with all three nodes in its broker list.  A subscriber on another node sees every
gateway; then the node most gateways are on is killed (SIGKILL, as a machine losing
power), and every gateway must be back on another node within 10 s, the retained
statuses right, and states from every gateway flowing again.  What the failover cost
is counted and printed (``pytest -s``; the figures are in docs/scaling.md)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from support.broker import Received, Recorder, recording
from support.harness import running, until
from support.nats_cluster import NatsCluster, NatsNode

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

GATEWAYS = 10
POLL_HZ = 10


def _config(i: int, line: str, urls: list[str]) -> dict[str, Any]:
    # each gateway lists every node, starting at its own: node 1 gets 4 of the 10.
    # States not retained: NATS keeps retained messages in JetStream, and holds every
    # later packet of the connection while it stores one, up to 4 s each while a dead
    # node's streams elect new leaders (docs/scaling.md).  Status, availability and
    # discovery stay retained.
    start = i % len(urls)
    return {"gateway_id": f"gw{i:02d}",
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "sensors": [{"name": "ah", "series": "AH", "poll_hz": POLL_HZ}]}],
            "mqtt": {"url": urls[start:] + urls[:start], "retain": False}}


def _seqs(messages: list[Received], gid: str) -> list[int]:
    return [json.loads(m.payload)["seq"] for m in messages if m.topic == f"imu/{gid}/ah/state"]


def _sampled(m: Received) -> datetime:
    return datetime.fromisoformat(json.loads(m.payload)["ts"].replace("Z", "+00:00"))


def _statuses(rec: Recorder, retained: bool = False) -> dict[str, str]:
    """Each gateway's latest status (``retained``: of those the broker had stored)."""
    out = {}
    for m in list(rec.messages):
        if m.topic.endswith("/status") and (m.retain or not retained):
            out[m.topic.split("/")[1]] = m.text
    return out


async def _retained_statuses(node: NatsNode) -> dict[str, str]:
    """The retained statuses a new subscriber to ``imu/+/status`` on ``node`` gets."""
    with recording(node, "imu/+/status", qos=0) as late:
        with contextlib.suppress(TimeoutError):
            await until(lambda: len(_statuses(late, retained=True)) == GATEWAYS, 5)
        return _statuses(late, retained=True)


@pytest.mark.slow
@pytest.mark.anyio
async def test_a_fleet_fails_over_when_the_busiest_node_dies(tmp_path: Path) -> None:
    ids = [f"gw{i:02d}" for i in range(GATEWAYS)]
    with NatsCluster(tmp_path) as cluster, contextlib.ExitStack() as lines:
        async with contextlib.AsyncExitStack() as fleet:
            await _fleet(cluster, lines, fleet, ids)


async def _fleet(cluster: NatsCluster, lines: contextlib.ExitStack,
                 fleet: contextlib.AsyncExitStack, ids: list[str]) -> None:
    urls = [node.url for node in cluster.nodes]
    busiest, watcher_node, fresh_node = cluster.nodes
    rec = lines.enter_context(recording(watcher_node, "imu/+/status", "imu/+/+/state",
                                       qos=0))
    # NATS may drop the subscriber too while it recovers: it must be back as soon as
    # NATS lets it, within a second (paho's own back-off doubles up to 2 min)
    rec.client.reconnect_delay_set(1, 1)
    gateways: list[Gateway] = []
    for i in range(GATEWAYS):
        line = lines.enter_context(simulated(
            [make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)]))
        gateways.append(await fleet.enter_async_context(
            running(_config(i, line.path, urls))))
    # every gateway's status and every sensor's state arrive on another node
    await until(lambda: _statuses(rec) == dict.fromkeys(ids, "online"), 30)
    await until(lambda: all(_seqs(list(rec.messages), gid) for gid in ids), 30)
    on = Counter(str(gw.mqtt.failover.current) for gw in gateways if gw.mqtt)
    assert on.most_common(1)[0] == (f"127.0.0.1:{busiest.port}", 4), on
    moving = [gw for gw in gateways
              if gw.mqtt and gw.mqtt.failover.current.port == busiest.port]

    # the steady rate into the cluster, as the subscriber gets it
    mark, t0 = len(rec.messages), time.monotonic()
    await until(lambda: len(rec.messages) >= mark + GATEWAYS * POLL_HZ * 3, 30)
    rate = (len(rec.messages) - mark) / (time.monotonic() - t0)

    before = {gid: max(_seqs(list(rec.messages), gid)) for gid in ids}
    led = [what for what, node in watcher_node.leaders().items() if node == busiest.name]
    killed_at, killed_wall = time.monotonic(), datetime.now(UTC)
    busiest.kill()
    # every gateway on the dead node is connected elsewhere, and its states flow
    elsewhere: dict[str, float] = {}

    def all_elsewhere() -> bool:
        for gw in moving:
            if gw.mqtt is not None and gw.mqtt.connected and \
                    gw.mqtt.failover.current.port != busiest.port:
                elsewhere.setdefault(gw.config.gateway_id, time.monotonic() - killed_at)
        return len(elsewhere) == len(moving)

    await until(all_elsewhere, 10)
    back: dict[str, float] = {}

    def all_back() -> bool:
        """Each gateway's first state sampled after the kill, and when it came."""
        for m in list(rec.messages):
            gid = m.topic.split("/")[1]
            if m.topic.endswith("/state") and gid not in back and \
                    _sampled(m) > killed_wall:
                back[gid] = m.at - killed_at
        return len(back) == GATEWAYS

    # The gateway's part is short: 0.5 s after the loss it probes the other nodes,
    # another probe every 0.5 s while none answers, and connects to the first that
    # does.  NATS's part is the election of new leaders for the dead node's JetStream
    # groups (4-9 s, fixed in nats-server): a node holds each MQTT connection that
    # needs one 4 s, then closes it unanswered.  The figures: docs/scaling.md.
    await until(all_back, 30)
    moved = [gw.config.gateway_id for gw in moving]
    failover = max(back[gid] for gid in moved)

    # no retained status is wrong: what a subscriber that comes now gets, on the third
    # node and on the watcher's (NATS serves retained messages from JetStream,
    # recovering too: a new subscriber every second, for up to 30 s)
    online = dict.fromkeys(ids, "online")
    deadline = time.monotonic() + 30
    while True:
        retained = await _retained_statuses(fresh_node)
        watched = await _retained_statuses(watcher_node)
        if (retained, watched) == (online, online) or time.monotonic() >= deadline:
            break
        await asyncio.sleep(1)
    history = {g: [(round(m.at - killed_at, 2), m.text) for m in list(rec.messages)
                   if m.topic == f"imu/{g}/status"] for g in ids}
    # every gateway's last word, as node 2's live subscriber heard it, is online; or it
    # said online after the kill, and the last word is a late will.  NATS publishes a
    # dead node's wills 5-10 s after the kill, from another node than the gateway's own
    # "online", and a live subscriber may get two publishers' messages in either order
    # (MQTT orders one publisher's only: seen once in CI, the retained status online).
    # The retained status, what every subscriber gets when it comes, must be right.
    assert all(h and (h[-1][1] == "online" or any(t > 0 and text == "online"
                                                  for t, text in h))
               for h in history.values()), history
    assert len(retained) == GATEWAYS, retained
    if retained != online or watched != online:
        # what node 3 serves to a subscriber of each wrong gateway's own topic, now
        exact = {}
        for g in sorted(g for g, text in retained.items() if text != "online"):
            with recording(fresh_node, f"imu/{g}/status", qos=0) as one:
                with contextlib.suppress(TimeoutError):
                    await until(lambda: bool(one.messages), 5)
                exact[g] = [(m.text, m.retain) for m in list(one.messages)]
        raise AssertionError(f"retained statuses on node 3: {retained}, on node 2: "
                             f"{watched}; each wrong one's own topic on node 3: {exact}; "
                             f"heard live on node 2: {history}")

    # what the failover cost: states of the moved gateways never seen
    mark = len(rec.messages)
    await until(lambda: len(rec.messages) >= mark + GATEWAYS * POLL_HZ, 10)
    lost = {}
    for gid in ids:
        seqs = sorted(set(_seqs(list(rec.messages), gid)))
        span = [s for s in seqs if s > before[gid] - POLL_HZ]
        lost[gid] = (span[-1] - span[0] + 1) - len(span)
    print(f"\nfleet: {GATEWAYS} gateways, {rate:.0f} messages/s into the cluster; "
          f"killed the node of {len(moved)} (it led {', '.join(led) or 'nothing'}): "
          f"all back on another node after "
          f"{failover:.2f} s at most (each: "
          f"{', '.join(f'{back[g]:.2f}' for g in moved)} s; connected elsewhere after "
          f"{', '.join(f'{elsewhere[g]:.2f}' for g in moved)} s; the subscriber dropped "
          f"by NATS at {[round(t - killed_at, 2) for t in rec.drops]} s); states lost per moved "
          f"gateway: {[lost[g] for g in moved]}, per other gateway: "
          f"{[lost[g] for g in ids if g not in moved]}")
    assert failover < 10
    # (not asserted: in some runs NATS also drops the surviving nodes' MQTT
    # connections while its JetStream groups elect, so the other gateways lose states
    # too; what was lost is the figure the test reports)
