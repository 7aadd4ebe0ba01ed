"""A front end that is not configured costs nothing, not even its imports
(docs/deployment.md, "Small boxes").

The real ``python -m imu_gateway run`` on a simulated line, under Python's own import
log (``-X importtime`` writes a line to stderr for every module the process imports,
whenever it does): run until the sensor is online (and the MQTT client connected to a
real mosquitto, when it has one), stopped with SIGINT, and the modules it imported in
all that time are read from that log.
"""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from importlib.metadata import version
from pathlib import Path
from typing import Any

import pytest
import yaml
from asyncua import Client, ua
from support.broker import Mosquitto
from support.harness import free_port

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

FAST = 115200
#: what each front end brings with it: its own modules and its libraries
STACKS = {
    "modbus": ("imu_gateway.frontends.modbus",),
    "mqtt": ("imu_gateway.frontends.mqtt", "imu_gateway.mqtt_link", "paho"),
    "sparkplug": ("imu_gateway.frontends.sparkplug", "imu_gateway.mqtt_link", "paho",
                  "google.protobuf"),
    "http": ("imu_gateway.frontends.rest", "fastapi", "starlette", "uvicorn",
             "prometheus_client"),
    "opcua": ("imu_gateway.frontends.opcua", "asyncua"),
}
#: libraries only front ends use (the bus needs pydantic, yaml, pyserial, pymodbus.pdu)
HEAVY = ("asyncua", "fastapi", "starlette", "uvicorn", "prometheus_client", "paho",
         "google.protobuf", "cryptography", "pymodbus.server")
_IMPORT_LINE = re.compile(r"^import time:\s+\d+ \|\s+\d+ \|\s*(\S+)$")


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def loaded(names: set[str], prefixes: tuple[str, ...]) -> list[str]:
    """The names among ``names`` in any of the packages ``prefixes``."""
    return sorted(n for n in names if any(_within(n, p) for p in prefixes))


def imports_of_run(config: dict[str, Any], folder: Path, ready: Callable[[str], bool],
                   then: Callable[[], None] = lambda: None,
                   env: dict[str, str] | None = None) -> set[str]:
    """Every module ``imu-gateway run`` on ``config`` imported from its start until
    its log showed everything ``ready`` waits for, ``then`` ran, and it stopped."""
    path = folder / "gateway.yaml"
    path.write_text(yaml.safe_dump(config))
    log: list[str] = []
    with subprocess.Popen([sys.executable, "-X", "importtime", "-m", "imu_gateway", "run",
                           "-c", str(path)], stderr=subprocess.PIPE, text=True,
                          env={**os.environ, **(env or {})}) as proc:
        watchdog = threading.Timer(60, proc.kill)  # a gateway that never gets there
        watchdog.start()
        assert proc.stderr is not None
        try:
            for line in proc.stderr:
                log.append(line)
                if ready("".join(log)):
                    then()
                    break
            proc.send_signal(2)  # SIGINT, as a user stops it
            log += proc.stderr.readlines()
        finally:
            watchdog.cancel()
            proc.kill()
    text = "".join(log)
    assert ready(text), f"the gateway did not get ready:\n{text[-3000:]}"
    assert proc.returncode == 0, text[-3000:]
    return {m.group(1) for line in log if (m := _IMPORT_LINE.match(line.rstrip("\n")))}


@pytest.fixture(scope="module")
def line() -> Iterator[str]:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)]) as sim:
        yield sim.path


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mosquitto]:
    with Mosquitto(tmp_path_factory.mktemp("broker")) as running:
        yield running


def bus_only(port: str) -> dict[str, Any]:
    return {"gateway_id": "lean", "buses": [{
        "name": "line", "port": port, "baudrate": FAST, "protocol": "native",
        "sensors": [{"name": "mast", "series": "AH", "poll_hz": 10}]}]}


def front_end(name: str, broker: Mosquitto, folder: Path) -> dict[str, Any]:
    """The config section that turns on ``name`` alone, on loopback."""
    listen = f"127.0.0.1:{free_port()}"
    sections: dict[str, dict[str, Any]] = {
        "modbus": {"modbus": {"listen": listen}},
        "mqtt": {"mqtt": {"url": broker.url, "homeassistant_discovery": True}},
        "sparkplug": {"mqtt": {"url": broker.url, "sparkplug": {
            "group_id": "lean", "plain_topics": False}}},
        "http": {"http": {"listen": listen}},
        "opcua": {"opcua": {"listen": listen, "allow_none": True,
                            "pki_dir": str(folder / "pki")}},
    }
    return sections[name]


def online(text: str) -> bool:
    return "sensor mast: online" in text


def test_a_bus_only_gateway_imports_no_front_end(line: str, tmp_path: Path) -> None:
    modules = imports_of_run(bus_only(line), tmp_path, online)
    assert "imu_gateway.bus.runner" in modules  # (the log is read right)
    assert loaded(modules, HEAVY) == []
    assert loaded(modules, ("imu_gateway.frontends",)) == []
    # the config file's text is kept as read; ruamel parses it when it is first shown,
    # saved or reloaded
    assert loaded(modules, ("ruamel",)) == []


@pytest.mark.parametrize("name", sorted(STACKS))
def test_a_front_end_alone_brings_only_its_own_stack(name: str, line: str,
                                                     broker: Mosquitto,
                                                     tmp_path: Path) -> None:
    config = {**bus_only(line), **front_end(name, broker, tmp_path)}

    def ready(text: str) -> bool:
        connected = name not in ("mqtt", "sparkplug") or "mqtt: connected to" in text
        return online(text) and connected

    modules = imports_of_run(config, tmp_path, ready)
    assert loaded(modules, STACKS[name]), f"{name}: its own stack is not in the log"
    others = tuple(p for other, stack in STACKS.items() if other != name for p in stack
                   if p not in STACKS[name])
    assert loaded(modules, others) == []
    # cryptography is OPC UA's (its certificates); Modbus TCP needs it for TLS only
    if name != "opcua":
        assert loaded(modules, ("cryptography",)) == []


def test_opcua_reads_the_standard_address_space_from_its_cache(line: str,
                                                                tmp_path: Path) -> None:
    """asyncua's standard nodes are built once, by a child process, into the cache
    folder; the next start loads them from there as they are used, and a client sees
    the same server."""
    cache, port = tmp_path / "cache", free_port()
    config = {**bus_only(line), "opcua": {"listen": f"127.0.0.1:{port}", "allow_none": True,
                                          "pki_dir": str(tmp_path / "pki")}}
    seen: list[Any] = []

    async def read() -> None:
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index("urn:imu-gateway")
            state = client.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
            pitch = client.get_node(ua.NodeId("lean.Sensors.mast.Angles.pitch", idx))
            seen.extend([await state.read_value(), await pitch.read_value()])

    for start in ("building", "cached"):
        seen.clear()
        modules = imports_of_run(config, tmp_path, online, lambda: asyncio.run(read()),
                                 env={"CACHE_DIRECTORY": str(cache)})
        # the gateway's process never builds the space: the child did, or the cache has it
        assert "asyncua.server.standard_address_space" not in modules, start
        assert [p.name for p in cache.iterdir()] == \
            [f"opcua-standard-space-{version('asyncua')}-py{sys.version_info[0]}."
             f"{sys.version_info[1]}"], start
        assert seen[0] == ua.ServerState.Running and isinstance(seen[1], float), start


def test_the_bus_thread_can_be_found_and_pinned_as_the_docs_say(line: str,
                                                                  tmp_path: Path) -> None:
    """docs/deployment.md, "Small boxes": the bus thread is "bus" in
    ``/proc/PID/task/*/comm``; ``taskset -p -c 0 TID`` pins it, and the bus goes on."""
    path = tmp_path / "gateway.yaml"
    path.write_text(yaml.safe_dump(bus_only(line)))
    with subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(path),
                           "--stats-interval", "0.2"], stderr=subprocess.PIPE,
                          text=True) as proc:
        watchdog = threading.Timer(60, proc.kill)
        watchdog.start()
        assert proc.stderr is not None
        try:
            lines = iter(proc.stderr)
            assert any(online(text) for text in lines)
            tasks = Path(f"/proc/{proc.pid}/task")
            named = {t.name: (t / "comm").read_text().strip() for t in tasks.iterdir()}
            bus = [tid for tid, comm in named.items() if comm == "bus"]
            assert len(bus) == 1, named
            subprocess.run(["taskset", "-p", "-c", "0", bus[0]], check=True,
                           capture_output=True)
            status = (tasks / bus[0] / "status").read_text()
            assert "Cpus_allowed_list:\t0\n" in status
            # the stats lines that follow: the bus still reads, pinned
            busy = re.compile(r"bus line: ([0-9.]+) transactions/s")
            rates = (float(m.group(1)) for text in lines if (m := busy.search(text)))
            next(rates)  # (the first may span the moment of the pinning)
            assert next(rates) > 5
        finally:
            watchdog.cancel()
            proc.send_signal(2)
            proc.communicate(timeout=20)
