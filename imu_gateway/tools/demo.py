"""``imu-gateway demo``: the whole gateway on simulated sensors, no hardware.

Two simulated serial lines, each on its own pseudo-terminal: a native line with an AH
sensor (polled) and a MINS sensor (streaming its own auto-output), and a Modbus-RTU
line with a VG sensor.  Every interface is up: Modbus TCP (writes allowed), REST with
commands (a bearer token made for this run), the dashboard, and MQTT when a broker is
reachable (the client keeps retrying in the background when it is not).  The ready
command lines printed at start are the quickest tour.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import shlex
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from ..app import Gateway, run_until_signalled
from ..commands import CATALOGUE
from ..config import Broker, GatewayConfig, config_from_dict
from ..model import Series, WireProtocol
from ..simulator import SimulatorThread, make_sensor
from ..simulator.motion import Motion

BAUD = 115200


@dataclass(frozen=True)
class DemoSensor:
    name: str
    series: Series
    poll_hz: float = 0.0
    stream_hz: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class DemoLine:
    name: str
    protocol: WireProtocol
    sensors: tuple[DemoSensor, ...]


LINES = (
    DemoLine("line-a", WireProtocol.NATIVE, (
        DemoSensor("boom", Series.AH, poll_hz=20, seed=1),
        DemoSensor("mast", Series.MINS, stream_hz=25, seed=2),
    )),
    DemoLine("line-b", WireProtocol.MODBUS, (
        DemoSensor("arm", Series.VG, poll_hz=10, seed=3),
    )),
)


@dataclass(frozen=True)
class DemoOptions:
    modbus_port: int = 5020
    http_port: int = 8080
    mqtt_url: str = "mqtt://localhost:1883"
    host: str = "127.0.0.1"
    opcua_port: int = 4840
    #: the OPC UA server's certificate and key (a temporary folder: the demo's own)
    pki_dir: str = "opcua-pki"


def _addresses(line: DemoLine) -> Iterator[tuple[DemoSensor, int]]:
    first = 0 if line.protocol is WireProtocol.NATIVE else 1
    for index, sensor in enumerate(line.sensors):
        yield sensor, first + index


def demo_config(ports: dict[str, str], options: DemoOptions, token: str) -> GatewayConfig:
    """The gateway's config for the simulated lines at ``ports`` (line name -> pty)."""
    return config_from_dict({
        "gateway_id": "demo",
        "buses": [{
            "name": line.name, "port": ports[line.name], "baudrate": BAUD,
            "protocol": line.protocol.name.lower(),
            "sensors": [{"name": s.name, "series": s.series.name, "address": address,
                         "poll_hz": s.poll_hz, "stream_hz": s.stream_hz}
                        for s, address in _addresses(line)],
        } for line in LINES],
        "modbus": {"listen": f"{options.host}:{options.modbus_port}", "allow_writes": True},
        # MQTT 5: a request's response topic and correlation data are honoured, so
        # mosquitto_rr (which speaks 5 only) gets its answer
        "mqtt": {"url": options.mqtt_url, "allow_commands": True, "protocol": "5"},
        "http": {"listen": f"{options.host}:{options.http_port}", "token": token,
                 "allow_commands": True},
        # security mode None too, so that a client on this machine needs no certificate
        "opcua": {"listen": f"{options.host}:{options.opcua_port}", "allow_none": True,
                  "pki_dir": options.pki_dir},
    }, env={})


def banner(gateway: Gateway, token: str) -> str:
    """What the demo prints once every interface is up."""
    config = gateway.config
    assert config.http is not None and gateway.http is not None and gateway.modbus is not None
    listen = config.http.listen.host
    host = "localhost" if listen in ("127.0.0.1", "0.0.0.0", "::") else listen
    http_port, modbus_port = gateway.http.port, gateway.modbus.port
    base = f"http://{host}:{http_port}"
    rows = []
    for bus, sensor in config.iter_sensors():
        how = f"streaming {sensor.stream_hz:g} Hz" if sensor.stream_hz else \
            f"polled {sensor.poll_hz:g} Hz"
        rows.append(f"  {sensor.name:<6} {sensor.series.name:<5} {bus.protocol.name.lower():<7}"
                    f"{bus.name:<8} Modbus unit {sensor.unit_id}   {how}")
    first, sensor = next(iter(gateway.sensors.items()))
    # the first catalogue command with arguments this sensor has
    spec = next(s for s in CATALOGUE.values() if s.example and sensor.series in s.series)
    command = shlex.join(["curl", "-X", "POST", "-H", f"Authorization: Bearer {token}",
                          "-H", "Content-Type: application/json",
                          "-d", json.dumps(dict(spec.example)),
                          f"{base}/api/v1/sensors/{first}/commands/{spec.name}"])
    lines = [
        f"imu-gateway demo: {len(gateway.sensors)} simulated sensors on "
        f"{len(config.buses)} simulated serial lines at {BAUD} baud (no hardware)",
        *rows,
        f"These are simulated sensors; each line counts its timeouts and bad frames at "
        f"{base}/api/v1/buses",
        "",
        f"Dashboard   {base}/",
        f"REST        curl {base}/api/v1/sensors/{first}/reading",
        f"            curl -N {base}/api/v1/stream      (live, Server-Sent Events)",
        f"Commands    {command}",
        f"Metrics     curl {base}/metrics",
        f"Modbus TCP  mbpoll -m tcp -p {modbus_port} -a 1 -r 101 -c 16 -t 4:float -B -1 {host}",
    ]
    if gateway.opcua is not None:
        # asyncua's command-line tools come with the gateway (beside this Python)
        uaread = Path(sys.executable).parent / "uaread"
        pitch = f"ns={gateway.opcua.idx};s={config.gateway_id}.Sensors.{first}.Angles.pitch"
        lines.append(f"OPC UA      {uaread} -u opc.tcp://{host}:{gateway.opcua.port}/ "
                     f"-n '{pitch}'   (security None or Basic256Sha256)")
    if config.mqtt is not None:
        mqtt = config.mqtt
        prefix = f"{mqtt.base_topic}/{config.gateway_id}"
        broker = mqtt.brokers[0]
        lines.append(f"MQTT        mosquitto_sub -h {broker.host} -p {broker.port} -v "
                     f"-t '{prefix}/#'   (MQTT 5; the demo publishes to the broker it "
                     f"finds at {mqtt.url}, yours if one runs there, and clears its retained "
                     "messages when it stops; retried in the background while none is "
                     "there)")
        lines.append(f"            mosquitto_rr -h {broker.host} -p {broker.port} "
                     f"-t {prefix}/{first}/cmd/read_settings -e {prefix}/replies -m '{{}}'")
    lines += [f"Token       {token}   (an admin's: REST's bearer token, and the dashboard's "
              "Log in with no user name)", "", "Stop with Ctrl-C."]
    return "\n".join(lines)


def run_demo(options: DemoOptions) -> None:
    """Run until SIGINT or SIGTERM.  Raises ``app.StartupError`` when a port is taken."""
    token = secrets.token_urlsafe(12)
    with ExitStack() as stack:
        pki = stack.enter_context(tempfile.TemporaryDirectory(prefix="imu-gateway-demo-"))
        options = replace(options, pki_dir=pki)
        ports = {}
        for line in LINES:
            sims = [make_sensor(line.protocol, s.series, address, baud=BAUD,
                                source=Motion.from_seed(s.seed))
                    for s, address in _addresses(line)]
            ports[line.name] = stack.enter_context(SimulatorThread(sims)).path
        config = demo_config(ports, options, token)

        retained: list[str] = []

        def started(gateway: Gateway) -> None:
            if gateway.mqtt is not None:  # what it retains: its own topics, its claims
                # of the gateway id and client id (docs/mqtt.md), its discovery
                retained.extend([f"{gateway.mqtt.prefix}/#", *gateway.mqtt.identity.claim_topics,
                                 *gateway.mqtt.discovery])
            print(banner(gateway, token), flush=True)

        asyncio.run(run_until_signalled(config, on_started=started))
        if config.mqtt is not None and retained:
            cleared = clear_retained(config.mqtt.brokers[0], config.mqtt.tls, retained)
            if cleared:
                print(f"imu-gateway demo: cleared its {cleared} retained messages from "
                      f"{config.mqtt.brokers[0]}", file=sys.stderr, flush=True)


def clear_retained(broker: Broker, tls: bool, topics: list[str],
                   timeout: float = 10.0) -> int:
    """Deletes the retained messages on ``topics`` (filters) from the broker: the demo
    publishes to a broker it did not set up, often the user's own, and must not leave
    sensors there saying "ok" after it stopped.  Returns how many were cleared (0 when
    the broker is not reachable: nothing was left there then)."""
    client = paho.Client(CallbackAPIVersion.VERSION2, protocol=paho.MQTTv311)
    if tls:
        client.tls_set()
    found: set[str] = set()
    # A message published after the subscriptions comes back after their retained
    # messages (the broker sends those at the SUBSCRIBE): its arrival ends the wait.
    marker = f"{topics[0].removesuffix('/#')}/demo-stopped/{secrets.token_hex(4)}"
    done = threading.Event()

    def on_connect(c: paho.Client, *_: Any) -> None:
        c.subscribe([(topic, 0) for topic in [*topics, marker]])
        c.publish(marker, b"", qos=1)

    def on_message(c: paho.Client, _: Any, message: paho.MQTTMessage) -> None:
        if message.topic == marker:
            done.set()
        elif message.retain and message.payload:
            found.add(message.topic)

    client.on_connect, client.on_message = on_connect, on_message
    try:
        client.connect(broker.host, broker.port, keepalive=10)
    except OSError:
        return 0
    client.loop_start()
    try:
        if not done.wait(timeout):
            return 0
        sent = [client.publish(topic, b"", qos=1, retain=True) for topic in sorted(found)]
        for info in sent:
            info.wait_for_publish(timeout)
        return len(sent)
    finally:
        client.disconnect()
        client.loop_stop()
