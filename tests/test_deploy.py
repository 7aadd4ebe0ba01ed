"""The deployment files of ``deploy/``: the systemd unit and its user, the Docker image
and compose setup with its mosquitto broker, the udev rules and the example configs.

Everything is checked against the real tools where this machine has them
(``systemd-analyze``, ``systemd-sysusers``, ``mosquitto``, the ``imu-gateway`` CLI)
and against each other: the paths, ports, users and names one file gives must be the
ones the others use.  The Docker daemon is never needed.
"""

from __future__ import annotations

import http.server
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
import yaml
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode
from support.broker import Mosquitto
from support.harness import free_port

from imu_gateway.config import GatewayConfig, load_config
from imu_gateway.tools.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
UNIT = DEPLOY / "systemd" / "imu-gateway.service"
SYSUSERS = DEPLOY / "systemd" / "imu-gateway.sysusers.conf"
DOCKER = DEPLOY / "docker"
DOCKERFILE = DOCKER / "Dockerfile"
COMPOSE = DOCKER / "compose.yaml"
MOSQUITTO = DOCKER / "mosquitto"
UDEV = DEPLOY / "udev" / "99-imu-gateway.rules"
EXAMPLES = sorted((DEPLOY / "examples").glob("*.yaml"))
COMPOSE_CONFIG = DOCKER / "gateway.yaml"
ALL_CONFIGS = [*EXAMPLES, COMPOSE_CONFIG]
EXEC_START = "/usr/local/bin/imu-gateway run -c /etc/imu-gateway/gateway.yaml"
SECRETS = {"MQTT_PASSWORD": "demo-gateway", "HTTP_TOKEN": "test-token"}


def env_vars(path: Path) -> set[str]:
    """The ``${NAME}``s of a config file (``$${`` is a literal)."""
    return set(re.findall(r"(?<!\$)\$\{([A-Za-z_][A-Za-z0-9_]*)\}", path.read_text()))




def cli_binary() -> Path:
    """The ``imu-gateway`` console script of the Python running the tests."""
    beside = Path(sys.executable).parent / "imu-gateway"
    found = beside if beside.exists() else shutil.which("imu-gateway")
    if found is None:
        pytest.skip("the imu-gateway console script is not installed (pip install -e .)")
    return Path(found)


def check_config(path: Path, env: dict[str, str]) -> subprocess.Popen[str]:
    """``imu-gateway check-config -c PATH`` started with exactly these secrets in the
    environment (any of ours inherited from the caller's removed)."""
    clean = {k: v for k, v in os.environ.items() if k not in SECRETS}
    return subprocess.Popen([str(cli_binary()), "check-config", "-c", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**clean, **env})


@pytest.fixture(scope="module")
def checked() -> dict[tuple[str, bool], tuple[int, str, str]]:
    """Every config through the real CLI, all at once (each takes a Python start-up):
    (file name, secrets given) -> (exit status, stdout, stderr)."""
    started = {}
    for path in ALL_CONFIGS:
        names = env_vars(path)
        started[path.name, True] = check_config(path, {n: SECRETS[n] for n in names})
        if names:
            started[path.name, False] = check_config(path, {})
    done = {}
    for key, process in started.items():
        stdout, stderr = process.communicate(timeout=60)
        done[key] = (process.returncode, stdout, stderr)
    return done


@pytest.mark.parametrize("path", ALL_CONFIGS, ids=lambda p: p.name)
def test_config_passes_check_config(
        path: Path, checked: dict[tuple[str, bool], tuple[int, str, str]]) -> None:
    names = env_vars(path)
    assert names <= set(SECRETS), f"{path.name} uses unknown variables {names - set(SECRETS)}"
    status, stdout, stderr = checked[path.name, True]
    assert status == 0, stderr
    assert stdout.startswith("config OK: ")
    if names:  # the secrets really come from the environment
        status, _, stderr = checked[path.name, False]
        assert status == 2
        for name in names:
            assert f"environment variable {name} is not set" in stderr


def load(path: Path) -> GatewayConfig:
    with pytest.MonkeyPatch.context() as patch:
        for name, value in SECRETS.items():
            patch.setenv(name, value)
        return load_config(path)


def test_examples_are_the_promised_setups() -> None:
    by_name = {p.stem: load(p) for p in EXAMPLES}
    assert set(by_name) == {"single-native", "mixed-bus", "modbus-rtu-only"}

    single = by_name["single-native"]
    [(bus, sensor)] = list(single.iter_sensors())
    assert (bus.protocol.name, sensor.series.name) == ("NATIVE", "AH")

    mixed = by_name["mixed-bus"]
    assert {b.protocol.name for b in mixed.buses} == {"NATIVE", "MODBUS"}
    assert len({s.series for _, s in mixed.iter_sensors()}) >= 3
    assert sum(1 for _, s in mixed.iter_sensors() if s.stream_hz > 0) == 1
    assert set(mixed.interfaces()) == {"modbus", "mqtt", "http"}
    assert env_vars(EXAMPLES[0].parent / "mixed-bus.yaml") == {"MQTT_PASSWORD", "HTTP_TOKEN"}
    assert mixed.mqtt is not None and mixed.mqtt.password == SECRETS["MQTT_PASSWORD"]

    rtu = by_name["modbus-rtu-only"]
    assert {b.protocol.name for b in rtu.buses} == {"MODBUS"}
    sensors = [s for _, s in rtu.iter_sensors()]
    assert len(sensors) >= 3 and {s.series.name for s in sensors} <= {"VG", "IMU"}
    assert all(s.raw_unit_id is not None for s in sensors)
    assert rtu.modbus is not None and rtu.modbus.listen is not None
    assert rtu.modbus.listen.port == 502


def test_examples_use_no_tls_files() -> None:
    """check-config needs ca_file/certfile/keyfile to exist: the examples name none."""
    for path in ALL_CONFIGS:
        config = load(path)
        if config.mqtt is not None:
            assert (config.mqtt.ca_file, config.mqtt.certfile, config.mqtt.keyfile) == \
                (None, None, None), path.name


# ------------------------------------------------------------------ systemd


def unit_settings(path: Path) -> dict[str, dict[str, list[str]]]:
    """A unit file as section -> key -> values (keys such as DeviceAllow repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            current = sections.setdefault(line.strip("[]"), {})
            continue
        assert current is not None, f"{raw!r} outside a section"
        assert not line.endswith("\\"), "no continuation lines, please"
        key, _, value = line.partition("=")
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def test_unit_runs_the_gateway_as_its_own_user_with_the_serial_ports() -> None:
    service = unit_settings(UNIT)["Service"]
    one = {key: values[-1] for key, values in service.items()}
    assert one["ExecStart"] == EXEC_START
    assert (one["User"], one["SupplementaryGroups"]) == ("imu-gateway", "dialout")
    assert one["EnvironmentFile"] == "-/etc/imu-gateway/env"
    assert one["Restart"] == "on-failure" and float(one["RestartSec"]) > 0
    assert one["KillSignal"] in {"SIGINT", "SIGTERM"} and "TimeoutStopSec" in one
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp", "ProtectKernelTunables",
                "ProtectKernelModules", "ProtectControlGroups"):
        assert one[key] == "yes", key
    assert one["ProtectSystem"] == "strict"
    assert one["CapabilityBoundingSet"] == "" and one["AmbientCapabilities"] == ""
    # the bus master's timing on a loaded machine: systemd grants real-time scheduling,
    # the process itself may not take it
    assert (one["CPUSchedulingPolicy"], one["RestrictRealtime"]) == ("fifo", "yes")
    assert 1 <= int(one["CPUSchedulingPriority"]) <= 49
    assert set(one["RestrictAddressFamilies"].split()) == {"AF_INET", "AF_INET6", "AF_UNIX"}
    # serial adapters must stay reachable: a closed device policy that lets them in,
    # and no PrivateDevices (it would hide them)
    assert one["DevicePolicy"] == "closed"
    allowed = {tuple(v.split()) for v in service["DeviceAllow"]}
    assert {("char-ttyUSB", "rw"), ("char-ttyS", "rw"), ("char-ttyACM", "rw")} <= allowed
    assert service.get("PrivateDevices", ["no"])[-1] == "no"
    assert unit_settings(UNIT)["Install"]["WantedBy"] == ["multi-user.target"]


def test_unit_command_line_is_what_the_cli_accepts() -> None:
    args = build_parser().parse_args(shlex.split(EXEC_START)[1:])
    assert (args.command, args.config) == ("run", "/etc/imu-gateway/gateway.yaml")


def test_unit_and_deployment_guide_name_one_install_path() -> None:
    """The unit's own comment and docs/deployment.md install to the same place."""
    pattern = r"/opt/imu-gateway/[\w/]*bin/imu-gateway\b"
    in_unit = set(re.findall(pattern, UNIT.read_text()))
    in_guide = set(re.findall(pattern, (ROOT / "docs" / "deployment.md").read_text()))
    assert in_unit and in_unit <= in_guide, (in_unit, in_guide)


def test_unit_documents_port_502() -> None:
    text = UNIT.read_text()
    assert "AmbientCapabilities=CAP_NET_BIND_SERVICE" in text
    assert "CapabilityBoundingSet=CAP_NET_BIND_SERVICE" in text


def runnable_unit(tmp_path: Path) -> Path:
    """The unit with ExecStart at this checkout's console script: ``verify`` checks
    that the binary exists."""
    unit = tmp_path / "imu-gateway.service"
    unit.write_text(UNIT.read_text().replace("/usr/local/bin/imu-gateway", str(cli_binary())))
    return unit


def systemd_analyze() -> str:
    path = shutil.which("systemd-analyze")
    if path is None:
        pytest.skip("systemd-analyze is not installed (Debian: apt-get install systemd)")
    return path


def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    tool = systemd_analyze()
    unit = runnable_unit(tmp_path)
    done = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True,
                          timeout=30, check=False, env={**os.environ, "SYSTEMD_PAGER": ""})
    ours = [line for line in (done.stdout + done.stderr).splitlines()
            if "imu-gateway" in line]
    assert done.returncode == 0 and not ours, done.stdout + done.stderr


def test_unit_exposure_is_low(tmp_path: Path) -> None:
    """``systemd-analyze security`` rates the sandbox; 1.8 when written, "OK" up to 3.9."""
    tool = systemd_analyze()
    unit = runnable_unit(tmp_path)
    done = subprocess.run([tool, "security", "--offline=true", "--no-pager", str(unit)],
                          capture_output=True, text=True, timeout=30, check=False)
    if "--offline" in done.stderr and "unrecognized" in done.stderr:
        pytest.skip("this systemd-analyze has no security --offline (systemd < 250)")
    found = re.search(r"Overall exposure level for \S+: (\d+\.\d)", done.stdout)
    assert found, done.stdout + done.stderr
    assert float(found.group(1)) <= 2.5, done.stdout


def test_sysusers_creates_the_user_in_dialout(tmp_path: Path) -> None:
    tool = shutil.which("systemd-sysusers")
    if tool is None:
        pytest.skip("systemd-sysusers is not installed (Debian: apt-get install systemd)")
    etc = tmp_path / "etc"
    etc.mkdir()
    (etc / "passwd").write_text("root:x:0:0:root:/root:/bin/sh\n")
    (etc / "group").write_text("root:x:0:\ndialout:x:20:\n")
    done = subprocess.run([tool, f"--root={tmp_path}", str(SYSUSERS)], capture_output=True,
                          text=True, timeout=30, check=False)
    assert done.returncode == 0, done.stderr
    users = {line.split(":")[0]: line.split(":") for line in (etc / "passwd").read_text()
             .splitlines()}
    assert users["imu-gateway"][6] == "/usr/sbin/nologin"
    groups = {line.split(":")[0]: line.split(":") for line in (etc / "group").read_text()
              .splitlines()}
    assert "imu-gateway" in groups["dialout"][3].split(",")
    assert "imu-gateway" in groups  # Group=imu-gateway of the unit exists


def test_env_example_names_the_secrets_of_the_examples() -> None:
    names = {line.split("=")[0] for line in (DEPLOY / "systemd" / "env.example").read_text()
             .splitlines() if line and not line.startswith("#")}
    used = set().union(*(env_vars(p) for p in ALL_CONFIGS))
    assert used <= names


# ------------------------------------------------------------------ Docker


def dockerfile() -> list[tuple[str, str]]:
    """The Dockerfile as (INSTRUCTION, arguments), continuation lines joined."""
    instructions: list[tuple[str, str]] = []
    pending = ""
    for raw in DOCKERFILE.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        word, _, rest = (pending + line).partition(" ")
        instructions.append((word.upper(), rest.strip()))
        pending = ""
    assert not pending
    return instructions


def docker_one(name: str) -> str:
    found = [args for word, args in dockerfile() if word == name]
    assert len(found) == 1, f"{name}: {found}"
    return found[0]


def compose() -> dict[str, Any]:
    data = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(data, dict)
    return data


def test_dockerfile_builds_a_non_root_gateway_image() -> None:
    assert docker_one("FROM") == "python:3.11-slim"
    user = docker_one("USER")
    assert user not in {"root", "0"}
    useradd = [args for word, args in dockerfile() if word == "RUN" and "useradd" in args]
    assert len(useradd) == 1 and "--groups dialout" in useradd[0]
    assert useradd[0].split()[-1] == user
    assert any(word == "RUN" and "pip install ." in args for word, args in dockerfile())
    # the sources COPY names exist in the build context (the repository's root), and
    # Dockerfile.dockerignore lets them through
    ignore = (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
    for word, args in dockerfile():
        if word == "COPY":
            *sources, _ = args.split()
            for source in sources:
                assert (ROOT / source).exists(), source
                assert f"!{source.rstrip('/')}" in {line.rstrip("/") for line in ignore}, \
                    source


def test_dockerfile_command_and_healthcheck() -> None:
    entry, cmd = json.loads(docker_one("ENTRYPOINT")), json.loads(docker_one("CMD"))
    assert entry == ["imu-gateway"]
    args = build_parser().parse_args(cmd)
    assert (args.command, args.config) == ("run", "/etc/imu-gateway/gateway.yaml")
    health = docker_one("HEALTHCHECK")
    script = json.loads(health.split(" CMD ", 1)[1])
    assert script[0] == "python"
    copied = [args.split() for word, args in dockerfile() if word == "COPY"
              and args.split()[-1] == script[1]]
    assert copied == [["deploy/docker/healthcheck.py", script[1]]]
    assert "/api/v1/health" in (DOCKER / "healthcheck.py").read_text()
    assert docker_one("STOPSIGNAL") in {"SIGTERM", "SIGINT"}


def test_compose_services_fit_the_image_and_the_config() -> None:
    data = compose()
    services = data["services"]
    assert set(services) == {"gateway", "mosquitto"}
    gateway, broker = services["gateway"], services["mosquitto"]

    build = gateway["build"]
    context = (COMPOSE.parent / build["context"]).resolve()
    assert context == ROOT and (context / build["dockerfile"]).resolve() == DOCKERFILE
    assert "mosquitto" in gateway["depends_on"]

    # the config it mounts is where the image's CMD looks, and is gateway.yaml here
    cmd = json.loads(docker_one("CMD"))
    config_path = cmd[cmd.index("-c") + 1]
    mounts = dict(reversed(v.split(":")[:2]) for v in gateway["volumes"])
    assert (COMPOSE.parent / mounts[config_path]).resolve() == COMPOSE_CONFIG

    config = load(COMPOSE_CONFIG)
    assert config.mqtt is not None and config.mqtt.brokers[0].host == "mosquitto"
    assert config.gateway_id != socket.gethostname()  # set: a container's name is random
    # the devices it passes in are the config's bus ports
    devices = {d.split(":")[1] for d in gateway["devices"]}
    assert devices == {bus.port for bus in config.buses}
    # published ports: the config's listening ports, which the image EXPOSEs
    listens = {config.modbus.listen.port if config.modbus and config.modbus.listen else None,
               config.http.listen.port if config.http else None} - {None}
    container_ports = {int(str(p).split(":")[-1]) for p in gateway["ports"]}
    assert container_ports == listens == {int(p) for p in docker_one("EXPOSE").split()}
    # the container's loopback is not the host's: listen on every address
    assert config.modbus is not None and config.modbus.listen is not None
    assert config.modbus.listen.host == "0.0.0.0"
    assert config.http is not None and config.http.listen.host == "0.0.0.0"
    # secrets: gateway.env (from gateway.env.example) holds every ${VAR} of the config
    [env_file] = gateway["env_file"]
    example = (COMPOSE.parent / f"{env_file}.example").read_text()
    assert env_vars(COMPOSE_CONFIG) <= set(re.findall(r"^([A-Z_]+)=", example, re.M))
    ignored = (DOCKER / ".gitignore").read_text().split()
    assert env_file in ignored and "mosquitto/passwords" in ignored

    assert broker["image"] == "eclipse-mosquitto:2"
    assert "./mosquitto:/mosquitto/config:ro" in broker["volumes"]
    assert any(str(p).endswith(":1883") for p in broker["ports"])


def mosquitto_conf() -> dict[str, str]:
    settings = {}
    for line in (MOSQUITTO / "mosquitto.conf").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            key, _, value = line.strip().partition(" ")
            settings[key] = value
    return settings


def test_mosquitto_conf_needs_a_login_and_names_files_that_exist() -> None:
    conf = mosquitto_conf()
    assert conf["listener"] == "1883"
    assert conf["allow_anonymous"] == "false"
    # /mosquitto/config is deploy/docker/mosquitto (compose.yaml mounts it)
    for key in ("password_file", "acl_file"):
        assert conf[key].startswith("/mosquitto/config/")
    acl = MOSQUITTO / Path(conf["acl_file"]).name
    assert acl.is_file()
    passwords = MOSQUITTO / Path(conf["password_file"]).name
    # the real file is made by the user; the example shows how it looks
    assert passwords.with_name(passwords.name + ".example").is_file()
    example = passwords.with_name(passwords.name + ".example").read_text()
    assert "DEMO ONLY" in example.splitlines()[0]
    assert mqtt_users(acl) == {"gateway", "dashboard", "operator"}


def mqtt_users(acl: Path) -> set[str]:
    return {line.split()[1] for line in acl.read_text().splitlines()
            if line.startswith("user ")}


def test_docker_compose_config_when_available(tmp_path: Path) -> None:
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker CLI: compose.yaml is checked by the other tests")
    probe = subprocess.run([docker, "compose", "version"], capture_output=True, timeout=30,
                           check=False)
    if probe.returncode != 0:
        pytest.skip("the docker CLI has no compose plugin")
    copy = tmp_path / "deploy" / "docker"
    shutil.copytree(DOCKER, copy)
    (copy / "gateway.env").write_text((DOCKER / "gateway.env.example").read_text())
    done = subprocess.run([docker, "compose", "-f", str(copy / "compose.yaml"), "config",
                           "--quiet"], capture_output=True, text=True, timeout=30,
                          check=False)
    assert done.returncode == 0, done.stderr


# ------------------------------------------------------------------ the broker, live


def deploy_broker(folder: Path) -> Mosquitto:
    """Debian's mosquitto with deploy/docker/mosquitto's conf, ACL and example
    passwords, on a free loopback port."""
    conf = mosquitto_conf()
    return Mosquitto(folder, settings={
        "allow_anonymous": conf["allow_anonymous"],
        "password_file": str(MOSQUITTO / "passwords.example"),
        "acl_file": str(MOSQUITTO / Path(conf["acl_file"]).name)})


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    with deploy_broker(tmp_path) as running:
        yield running


class Client:
    """A paho client logged in as a user of passwords.example (password demo-USER)."""

    def __init__(self, broker: Mosquitto, user: str | None, *subscribe: str) -> None:
        self.messages: list[tuple[str, str]] = []
        self.lock = threading.Lock()
        self.client = paho.Client(CallbackAPIVersion.VERSION2)
        if user is not None:
            self.client.username_pw_set(user, f"demo-{user}")
        connected, subscribed = threading.Event(), threading.Event()
        self.reason: ReasonCode | None = None

        def on_connect(client: paho.Client, _u: Any, _f: Any, reason: ReasonCode,
                       _p: Any) -> None:
            self.reason = reason
            connected.set()
            for topic in subscribe:
                client.subscribe(topic, qos=1)

        def on_message(_c: paho.Client, _u: Any, message: paho.MQTTMessage) -> None:
            with self.lock:
                self.messages.append((message.topic, message.payload.decode()))

        self.client.on_connect = on_connect
        self.client.on_subscribe = lambda *_: subscribed.set()
        self.client.on_message = on_message
        self.client.connect("127.0.0.1", broker.port)
        self.client.loop_start()
        assert connected.wait(10)
        assert self.reason is not None
        if subscribe and not self.reason.is_failure:
            assert subscribed.wait(10)

    def publish(self, topic: str, payload: str) -> None:
        self.client.publish(topic, payload, qos=1).wait_for_publish(10)

    def got(self, topic: str) -> list[str]:
        with self.lock:
            return [p for t, p in self.messages if t == topic]

    def wait_for(self, topic: str, payload: str, timeout: float = 10) -> None:
        deadline = time.monotonic() + timeout
        while payload not in self.got(topic):
            assert time.monotonic() < deadline, f"no {payload!r} on {topic}: {self.messages}"
            time.sleep(0.01)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def test_broker_acl_gateway_publishes_dashboard_reads_operator_commands(
        broker: Mosquitto) -> None:
    clients: list[Client] = []
    try:
        anonymous = Client(broker, None)
        clients.append(anonymous)
        assert anonymous.reason is not None
        assert anonymous.reason.is_failure  # allow_anonymous false
        gateway = Client(broker, "gateway", "imu/+/+/cmd/#", "imu/+/+/alarm/+/ack")
        dashboard = Client(broker, "dashboard", "imu/#", "homeassistant/#")
        operator = Client(broker, "operator", "imu/#")
        clients += [gateway, dashboard, operator]

        gateway.publish("imu/gw/boom/state", '{"seq": 1}')
        gateway.publish("homeassistant/sensor/gw_boom_pitch/config", "{}")
        dashboard.wait_for("imu/gw/boom/state", '{"seq": 1}')
        dashboard.wait_for("homeassistant/sensor/gw_boom_pitch/config", "{}")
        operator.wait_for("imu/gw/boom/state", '{"seq": 1}')

        # denied: a dashboard's command, a dashboard's fake state, an operator's fake
        # result; then the operator's command, which arrives after all of them would
        dashboard.publish("imu/gw/boom/cmd/save", "{}")
        dashboard.publish("imu/gw/boom/alarm/boom_lean/ack", '{"by": "dashboard"}')
        dashboard.publish("imu/gw/boom/state", '{"seq": 666}')
        operator.publish("imu/gw/boom/cmd/save/result", '{"ok": true}')
        operator.publish("imu/gw/boom/alarm/boom_lean/ack", '{"by": "operator"}')
        operator.publish("imu/gw/boom/cmd/calibrate_gyro", "{}")
        gateway.wait_for("imu/gw/boom/alarm/boom_lean/ack", '{"by": "operator"}')
        gateway.wait_for("imu/gw/boom/cmd/calibrate_gyro", "{}")
        gateway.publish("imu/gw/boom/cmd/calibrate_gyro/result", '{"ok": true}')
        operator.wait_for("imu/gw/boom/cmd/calibrate_gyro/result", '{"ok": true}')
        assert gateway.got("imu/gw/boom/cmd/save") == []
        assert gateway.got("imu/gw/boom/alarm/boom_lean/ack") == ['{"by": "operator"}']
        assert gateway.got("imu/gw/boom/cmd/save/result") == []
        assert '{"seq": 666}' not in operator.got("imu/gw/boom/state")
    finally:
        for client in clients:
            client.close()


def test_compose_gateway_config_runs_against_the_broker(broker: Mosquitto,
                                                        tmp_path: Path) -> None:
    """The gateway of the compose setup, as configured, logs in to a broker with the
    shipped ACL as user "gateway", publishes its status and discovery, answers the
    image's health check, and says "offline" when stopped with SIGTERM.  The serial
    port does not exist here: the sensors are offline, the rest works."""
    http_port, modbus_port = free_port(), free_port()
    text = COMPOSE_CONFIG.read_text()
    text = text.replace("mqtt://mosquitto:1883", f"mqtt://127.0.0.1:{broker.port}")
    text = text.replace("0.0.0.0:8080", f"127.0.0.1:{http_port}")
    text = text.replace("0.0.0.0:5020", f"127.0.0.1:{modbus_port}")
    config = tmp_path / "gateway.yaml"
    config.write_text(text)
    gateway_id = load(COMPOSE_CONFIG).gateway_id
    dashboard = Client(broker, "dashboard", "imu/#", "homeassistant/#")
    env = {**os.environ, **SECRETS}
    process = subprocess.Popen([str(cli_binary()), "run", "-c", str(config)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               env=env)
    try:
        dashboard.wait_for(f"imu/{gateway_id}/status", "online")
        dashboard.wait_for(f"imu/{gateway_id}/boom/availability", "offline")
        deadline = time.monotonic() + 10
        while not any(t.startswith("homeassistant/") for t, _ in dashboard.messages):
            assert time.monotonic() < deadline, "no discovery config"
            time.sleep(0.01)
        health = subprocess.run(
            [sys.executable, str(DOCKER / "healthcheck.py")], capture_output=True, text=True,
            timeout=30, check=False,
            env={**env, "IMU_GATEWAY_HEALTH_URL": f"http://127.0.0.1:{http_port}/api/v1/health"})
        assert health.returncode == 0, health.stderr
        assert health.stdout.startswith("degraded")  # the port is missing: still healthy
    finally:
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=20)
        dashboard.close()
    assert process.returncode == 0, stderr
    assert dashboard.got(f"imu/{gateway_id}/status")[-1] == "offline"


# ------------------------------------------------------------------ the health check


class Health(http.server.BaseHTTPRequestHandler):
    status = 200

    def do_GET(self) -> None:
        ok = self.path == "/api/v1/health" and \
            self.headers.get("Authorization") in (None, "Bearer tok")
        body = json.dumps({"status": "ok", "sensors": {"ok": 1}}).encode()
        self.send_response(self.status if ok else 401)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *_: Any) -> None:
        pass


@pytest.fixture
def health_server() -> Iterator[http.server.HTTPServer]:
    server = http.server.HTTPServer(("127.0.0.1", 0), Health)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()
    thread.join()


def healthcheck(url: str, **env: str) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if k != "HTTP_TOKEN"}
    return subprocess.run([sys.executable, str(DOCKER / "healthcheck.py")],
                          capture_output=True, text=True, timeout=30, check=False,
                          env={**clean, "IMU_GATEWAY_HEALTH_URL": url, **env})


def test_healthcheck_exit_status(health_server: http.server.HTTPServer) -> None:
    port = health_server.server_address[1]
    url = f"http://127.0.0.1:{port}/api/v1/health"
    assert healthcheck(url).returncode == 0
    assert healthcheck(url, HTTP_TOKEN="tok").returncode == 0
    assert healthcheck(url, HTTP_TOKEN="wrong").returncode == 1
    assert healthcheck(f"http://127.0.0.1:{port}/nope").returncode == 1
    assert healthcheck(f"http://127.0.0.1:{free_port()}/api/v1/health").returncode == 1
    Health.status = 500
    try:
        assert healthcheck(url).returncode == 1
    finally:
        Health.status = 200


# ------------------------------------------------------------------ udev

MATCH_KEYS = {"ACTION", "SUBSYSTEM", "SUBSYSTEMS", "KERNEL", "KERNELS", "DRIVER", "DRIVERS",
              "ATTRS", "ENV", "ATTR", "TAG", "TAGS"}
ASSIGN_KEYS = {"SYMLINK", "GROUP", "MODE", "OWNER", "ATTR", "ENV", "TAG", "RUN", "NAME"}
TOKEN = re.compile(r'\s*([A-Z]+)(?:\{([A-Za-z0-9_]+)\})?\s*(==|!=|\+=|:=|=)\s*"([^"]*)"\s*')


def udev_rules() -> list[list[tuple[str, str | None, str, str]]]:
    rules = []
    for number, line in enumerate(UDEV.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        tokens = []
        for part in line.split(","):
            found = TOKEN.fullmatch(part)
            assert found, f"line {number}: cannot read {part!r}"
            key, attribute, op, value = found.groups()
            if op in {"==", "!="}:
                assert key in MATCH_KEYS, f"line {number}: {key} is not a match key"
            else:
                assert key in ASSIGN_KEYS, f"line {number}: {key} cannot be assigned"
            assert (attribute is not None) == (key in {"ATTR", "ATTRS", "ENV", "RUN"}), \
                f"line {number}: {key}"
            tokens.append((key, attribute, op, value))
        rules.append(tokens)
    return rules


def test_udev_rules_name_the_adapters_for_the_dialout_group() -> None:
    named = [rule for rule in udev_rules() if any(t[0] == "SYMLINK" for t in rule)]
    vendors = set()
    for rule in named:
        keys = {(key, attribute): (op, value) for key, attribute, op, value in rule}
        assert keys[("SUBSYSTEM", None)] == ("==", "tty")
        assert keys[("GROUP", None)] == ("=", "dialout")
        assert keys[("MODE", None)] == ("=", "0660")
        assert keys[("SYMLINK", None)][0] == "+="
        vendors.add((keys[("ATTRS", "idVendor")][1], keys[("ATTRS", "idProduct")][1]))
        # and one thing that tells two adapters of a kind apart
        assert ("ATTRS", "serial") in keys or ("KERNELS", None) in keys
    assert vendors == {("0403", "6001"), ("1a86", "7523")}


def test_udev_names_are_the_example_ports() -> None:
    names = {f"/dev/{t[3]}" for rule in udev_rules() for t in rule if t[0] == "SYMLINK"}
    ports = {bus.port for path in ALL_CONFIGS for bus in load(path).buses}
    assert ports == names


# ------------------------------------------------------------------ the docs


def test_deployment_doc_is_linked_and_names_the_files() -> None:
    assert "(docs/deployment.md)" in (ROOT / "README.md").read_text()
    doc = (ROOT / "docs" / "deployment.md").read_text()
    for path in (UNIT, SYSUSERS, DOCKERFILE, COMPOSE, UDEV, *EXAMPLES):
        assert str(path.relative_to(ROOT)) in doc, path
    for link in re.findall(r"\]\(([^)#]+)", doc):
        if not link.startswith("http"):
            assert (ROOT / "docs" / link).resolve().exists(), link
