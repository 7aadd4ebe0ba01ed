"""A real 3-node NATS cluster with JetStream and its MQTT listener on every node
(Debian's ``nats-server``), for the fleet test."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

from .harness import free_port


def find_nats_server() -> str:
    """Debian's, or the binary ``IMU_TEST_NATS_SERVER`` names (another NATS version,
    to compare: docs/scaling.md)."""
    if chosen := os.environ.get("IMU_TEST_NATS_SERVER"):
        if not Path(chosen).is_file():
            raise RuntimeError(f"IMU_TEST_NATS_SERVER={chosen}: no such file")
        return chosen
    for candidate in (shutil.which("nats-server"), "/usr/sbin/nats-server"):
        if candidate and Path(candidate).exists():
            return candidate
    raise RuntimeError("nats-server not found: scripts/bootstrap --test installs it")


class NatsNode:
    def __init__(self, folder: Path, name: str) -> None:
        self.folder, self.name = folder, name
        self.port = free_port()  # MQTT
        self.client_port, self.route_port, self.http_port = free_port(), free_port(), free_port()
        self.tls = None  # (the broker helpers' recorder asks)
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def config(self, routes: list[int]) -> Path:
        path = self.folder / f"{self.name}.conf"
        route_list = ", ".join(f"nats-route://127.0.0.1:{p}" for p in routes)
        path.write_text(f"""
server_name: {self.name}
listen: 127.0.0.1:{self.client_port}
http: 127.0.0.1:{self.http_port}
jetstream {{ store_dir: "{self.folder / ('js-' + self.name)}" }}
cluster {{ name: imu, listen: 127.0.0.1:{self.route_port}, routes: [{route_list}] }}
mqtt {{ listen: 127.0.0.1:{self.port} }}
""")
        return path

    def healthy(self) -> bool:
        url = f"http://127.0.0.1:{self.http_port}/healthz?js-enabled-only=true"
        with contextlib.suppress(OSError), urllib.request.urlopen(url, timeout=1) as answer:
            return bool(answer.status == 200)
        return False

    def leaders(self) -> dict[str, str]:
        """Which node leads what, as this node sees it: the JetStream meta group
        (``meta``) and each stream (NATS's MQTT keeps sessions, retained messages and
        QoS 1 messages in streams ``$MQTT_sess``, ``$MQTT_rmsgs``, ``$MQTT_msgs``)."""
        url = f"http://127.0.0.1:{self.http_port}/jsz?accounts=true&streams=true"
        with urllib.request.urlopen(url, timeout=2) as answer:
            info = json.load(answer)
        led = {"meta": str(info.get("meta_cluster", {}).get("leader"))}
        for account in info.get("account_details", []):
            for stream in account.get("stream_detail", []):
                led[stream["name"]] = str(stream.get("cluster", {}).get("leader"))
        return led

    def kill(self) -> None:
        """Gone at once, as a machine that loses power: SIGKILL."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(10)


class NatsCluster:
    def __init__(self, folder: Path, size: int = 3) -> None:
        self.nodes = [NatsNode(folder, f"n{i + 1}") for i in range(size)]

    def __enter__(self) -> NatsCluster:
        routes = [n.route_port for n in self.nodes]
        binary = find_nats_server()
        for node in self.nodes:
            # (the child keeps its own copy of the log's descriptor)
            with (node.folder / f"{node.name}.log").open("wb") as log:
                node.process = subprocess.Popen([binary, "-c", str(node.config(routes))],
                                                stdout=log, stderr=subprocess.STDOUT)
        try:
            self._wait_healthy()
        except BaseException:
            self.__exit__()  # the nodes that did start must not outlive the test
            raise
        return self

    def _wait_healthy(self) -> None:
        deadline = time.monotonic() + 60
        while not all(n.healthy() for n in self.nodes):
            for node in self.nodes:
                assert node.process is not None
                if node.process.poll() is not None:
                    raise RuntimeError(f"nats-server {node.name} exited: "
                                       f"{(node.folder / (node.name + '.log')).read_text()}")
            if time.monotonic() > deadline:
                raise RuntimeError("the NATS cluster did not become healthy in 60 s")
            time.sleep(0.1)

    def __exit__(self, *_: object) -> None:
        for node in self.nodes:
            if node.process is not None and node.process.poll() is None:
                node.process.terminate()
                node.process.wait(10)
