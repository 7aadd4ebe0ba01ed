"""A real mosquitto broker for the tests, and a recording MQTT client.

The broker is Debian's ``mosquitto`` (``scripts/bootstrap`` installs it), started on a
free loopback port with a config written for the test: anonymous or with a password
file, plain or TLS with a certificate authority made by ``openssl`` in the test.
It keeps nothing on disk, so a restart forgets every retained message: whatever is
retained afterwards was published again by the gateway.
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTProtocolVersion

from .harness import free_port


def find_mosquitto() -> str:
    path = shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/sbin")
    if path is None:
        raise RuntimeError("mosquitto is not installed: run scripts/bootstrap")
    return path




@dataclass(frozen=True)
class Tls:
    """Files of a certificate authority, a server and a client certificate."""

    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path


def make_tls(folder: Path) -> Tls:
    """A fresh CA signing a server certificate for 127.0.0.1/localhost and a client
    certificate, with ``openssl``."""
    folder.mkdir(parents=True, exist_ok=True)

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=folder)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj",
            "/CN=imu-gateway test CA", "-keyout", "ca.key", "-out", "ca.crt")
    for name, extra in (("server", "subjectAltName=IP:127.0.0.1,DNS:localhost"),
                        ("client", "extendedKeyUsage=clientAuth")):
        openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={name}",
                "-keyout", f"{name}.key", "-out", f"{name}.csr")
        (folder / f"{name}.ext").write_text(extra + "\n")
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
                "-CAcreateserial", "-days", "2", "-extfile", f"{name}.ext",
                "-out", f"{name}.crt")
    return Tls(folder / "ca.crt", folder / "server.crt", folder / "server.key",
               folder / "client.crt", folder / "client.key")


class BrokerLike(Protocol):
    """A broker the recorder can reach: mosquitto, or a NATS node's MQTT listener."""

    @property
    def port(self) -> int: ...

    @property
    def tls(self) -> Tls | None: ...


class Mosquitto:
    """One broker process; ``stop()`` and ``start()`` again keep the port."""

    def __init__(self, folder: Path, *, tls: Tls | None = None,
                 users: dict[str, str] | None = None,
                 settings: dict[str, str] | None = None) -> None:
        """``users``: a password file made for them; ``settings``: more config lines
        (``password_file``, ``acl_file``, ``allow_anonymous`` …), which win."""
        self.folder = folder
        self.port = free_port()
        self.tls = tls
        self.users = users
        self.settings = settings or {}
        self.process: subprocess.Popen[bytes] | None = None
        self.log = folder / "mosquitto.log"

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://127.0.0.1:{self.port}"

    def _config(self) -> Path:
        lines = [f"listener {self.port} 127.0.0.1", "persistence false",
                 f"log_dest file {self.log}", "log_type all",
                 # as root, mosquitto would become user "mosquitto", who cannot read
                 # the test's private folder
                 f"user {getpass.getuser()}"]
        settings = {"allow_anonymous": "true"}
        if self.users:
            passwords = self.folder / "passwords"
            passwords.write_text("")
            for user, password in self.users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(passwords), user, password],
                               check=True, capture_output=True)
            settings.update(allow_anonymous="false", password_file=str(passwords))
        if self.tls:
            settings.update(cafile=str(self.tls.ca), certfile=str(self.tls.server_cert),
                            keyfile=str(self.tls.server_key), require_certificate="true")
        settings.update(self.settings)
        lines += [f"{key} {value}" for key, value in settings.items()]
        path = self.folder / "mosquitto.conf"
        path.write_text("\n".join(lines) + "\n")
        return path

    def start(self) -> None:
        errors = self.folder / "mosquitto.stderr"
        with errors.open("wb") as stderr:  # the child keeps its own copy of the descriptor
            self.process = subprocess.Popen([find_mosquitto(), "-c", str(self._config())],
                                            stdout=subprocess.DEVNULL, stderr=stderr)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {errors.read_text()}")
            with contextlib.suppress(OSError), socket.create_connection(
                    ("127.0.0.1", self.port), timeout=0.5):
                return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start listening")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(10)
        self.process = None

    def __enter__(self) -> Mosquitto:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()


@dataclass(frozen=True)
class Received:
    topic: str
    payload: bytes
    retain: bool
    properties: Any
    at: float  # time.monotonic() on arrival

    @property
    def text(self) -> str:
        return self.payload.decode()


class Recorder:
    """A paho client that records every message of its subscriptions."""

    def __init__(self, broker: BrokerLike, *topics: str,
                 version: MQTTProtocolVersion = paho.MQTTv311,
                 username: str | None = None, password: str | None = None,
                 qos: int = 1) -> None:
        self.client = paho.Client(CallbackAPIVersion.VERSION2, protocol=version)
        self.qos = qos
        if username is not None:
            self.client.username_pw_set(username, password)
        if broker.tls is not None:
            self.client.tls_set(ca_certs=str(broker.tls.ca),
                                certfile=str(broker.tls.client_cert),
                                keyfile=str(broker.tls.client_key))
        self.topics = topics
        self.messages: list[Received] = []
        self.drops: list[float] = []  # when the broker dropped this client (monotonic)
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.client.on_connect = self._on_connect
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = self._on_message
        self.client.on_disconnect = lambda *_: self.drops.append(time.monotonic())
        self.client.connect("127.0.0.1", broker.port)
        self.client.loop_start()
        if topics and not self._subscribed.wait(10):
            raise RuntimeError("no SUBACK from the broker")

    def _on_connect(self, client: paho.Client, *_: Any) -> None:
        for topic in self.topics:
            client.subscribe(topic, qos=self.qos)

    def _on_message(self, client: paho.Client, userdata: Any,
                    message: paho.MQTTMessage) -> None:
        with self._lock:
            self.messages.append(Received(message.topic, bytes(message.payload),
                                          bool(message.retain), message.properties,
                                          time.monotonic()))

    def on(self, topic: str) -> list[Received]:
        with self._lock:
            return [m for m in self.messages if m.topic == topic]

    def last(self, topic: str) -> Received | None:
        found = self.on(topic)
        return found[-1] if found else None

    def clear(self) -> None:
        with self._lock:
            self.messages.clear()

    def wait(self, condition: Callable[[], object], timeout: float = 10.0) -> None:
        """Block until ``condition()`` is true (for use outside an event loop)."""
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f"condition not met within {timeout} s")
            time.sleep(0.01)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@contextlib.contextmanager
def recording(broker: BrokerLike, *topics: str, **options: Any) -> Iterator[Recorder]:
    recorder = Recorder(broker, *topics, **options)
    try:
        yield recorder
    finally:
        recorder.close()


class Gate:
    """A TCP relay to the broker that the test opens and shuts."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = free_port()
        self.shut = False
        self._pipes: set[asyncio.StreamWriter] = set()
        self._clients: set[asyncio.StreamWriter] = set()  # the client's side of each
        self._hold_broker_side = False
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> Gate:
        self._server = await asyncio.start_server(self._relay, "127.0.0.1", self.port)
        return self

    async def __aexit__(self, *_: object) -> None:
        self.cut()
        assert self._server is not None
        self._server.close()

    def cut(self, client_side_only: bool = False) -> None:
        """Shut: every relayed connection is closed, and new ones are refused.
        ``client_side_only``: the broker's side stays open, so the broker takes the
        connection for alive (as when a NAT box resets only the client's side)."""
        self.shut = True
        self._hold_broker_side = client_side_only
        for writer in list(self._clients if client_side_only else self._pipes):
            writer.close()

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.shut:
            writer.close()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.close()
            return
        self._pipes |= {writer, up_writer}
        self._clients.add(writer)
        await asyncio.gather(self._copy(reader, up_writer), self._copy(up_reader, writer))
        self._pipes.discard(writer)
        if up_writer.is_closing():  # (a broker's side held open stays, for cut() to close)
            self._pipes.discard(up_writer)
        self._clients.discard(writer)

    async def _copy(self, source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError, asyncio.IncompleteReadError):
            while data := await source.read(65536):
                sink.write(data)
                await sink.drain()
        if sink in self._clients or not self._hold_broker_side:
            sink.close()
