"""One gateway per ``gateway_id`` on a broker: the second says so and stays away.

Two gateways with one ``gateway_id`` would overwrite each other's retained messages,
and with one client id the broker would hand the session from one to the other at
every reconnect.  So each gateway process claims its id: a retained message on
``{base}/{gw}/instance`` names the process (a random instance id, host, pid, start
time), published before its status.

* **Before connecting** (with its real client id, which would take over a running
  gateway's session), the gateway connects a probe with a client id of its own, reads
  the retained status and claim, and sends itself an echo to know it has them.  A
  claim by another instance while the status is ``online`` is a live gateway of that
  id: this one logs who it is and does not connect; it looks again later (the other
  may go, and its will then says ``offline``).  Its own predecessor (same host, its
  pid gone: a crash and a restart faster than the broker's keep-alive notices) is
  not a rival.
* **While connected,** it listens to its claim topic: another instance's claim means
  two came up at once.  The earlier start keeps the id; the later one says so and
  disconnects cleanly (no will: the status stays the other's ``online``).
* **The client id** is claimed the same way, on ``{base}/_clients/{client_id}``: a
  gateway of another ``gateway_id`` set to the same ``client_id`` is found by the probe
  (the claim names its gateway, whose status and claim the probe then reads).
  (mosquitto 2.0 closes a taken-over connection without saying why, so the probe is
  the only reliable signal.)
* **The probe** itself (its own connection, its echo, hedged across the broker list)
  is the MQTT transport's: ``imu_gateway/mqtt_link/probe.py``.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import NamedTuple

import paho.mqtt.client as paho

from ...config import Broker
from ...mqtt_link.errors import BrokerUnreached, ProbeFailed
from ...mqtt_link.message import Message
from ...mqtt_link.probe import read_retained, read_retained_hedged
from .topics import CONTROL_QOS, Topics

log = logging.getLogger("imu_gateway.mqtt")

#: How long a gateway that found its id (or client id) in use waits before it looks again.
RIVAL_WAIT = 30.0
#: The largest pid Linux gives (``pid_max`` at most 2**22), and the latest start a
#: claim may carry (the year 9999): anything past them is a malformed claim.
MAX_PID, MAX_STARTED = 2**22, 253402300799.0


@dataclass(frozen=True, slots=True)
class Claim:
    """Who holds a ``gateway_id``: one gateway process."""

    instance: str
    host: str
    pid: int
    started: float  # Unix time
    gateway_id: str
    client_id: str

    @classmethod
    def mine(cls, gateway_id: str, client_id: str) -> Claim:
        return cls(uuid.uuid4().hex, socket.gethostname(), os.getpid(), round(time.time(), 3),
                   gateway_id, client_id)

    def payload(self) -> bytes:
        return json.dumps(asdict(self)).encode()

    @classmethod
    def parse(cls, payload: bytes) -> Claim | None:
        """A claim from its payload; None for anything else (an empty retained message
        clears the topic; a malformed one is nobody's)."""
        try:
            data = json.loads(payload)
            claim = cls(str(data["instance"]), str(data["host"]), int(data["pid"]),
                        float(data["started"]), str(data["gateway_id"]),
                        str(data["client_id"]))
        except (ValueError, KeyError, TypeError, ArithmeticError):  # 1e400, Infinity
            return None
        # Anyone with publish rights may write these topics: values a process or a
        # clock cannot have are nobody's too (a pid past the kernel's, a NaN start).
        if not (0 < claim.pid <= MAX_PID and 0 <= claim.started <= MAX_STARTED):
            return None
        return claim

    def describe(self) -> str:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started))
        return f"host {self.host}, pid {self.pid}, since {since}"

    def first(self, other: Claim) -> bool:
        """Whether this claim came before ``other`` (the earlier start keeps the id)."""
        return (self.started, self.instance) < (other.started, other.instance)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    return True


def live_rival(mine: Claim, status: str | None, theirs: Claim | None,
               alive: Callable[[int], bool] = pid_alive) -> Claim | None:
    """The other gateway holding this id now, if there is one."""
    if theirs is None or theirs.instance == mine.instance or status != "online":
        return None
    if theirs.host == mine.host and not alive(theirs.pid):
        return None  # this machine's gateway before a restart; its will is late
    # (A container's gateway is pid 1 after every restart, so a crashed predecessor
    # looks alive: the gateway then waits for its will, RIVAL_WAIT at a time.  Taking
    # the same pid for a predecessor would let two host-networked containers, both
    # pid 1 on one host name, take each other's session: the wait is the safe side.)
    return theirs


class Probed(NamedTuple):
    """What the probe before a connect found."""

    broker: Broker  # the broker that answered first: the connect goes there
    rival: Claim | None  # another live gateway holding this id there
    served: dict[str, bytes]  # the retained messages it serves now, of those asked for


class Identity:
    """This gateway's claim on its ``gateway_id``, and what it does about rivals."""

    def __init__(self, topics: Topics, client_id: str,
                 send_control: Callable[[Message], None]) -> None:
        self.topics, self.client_id, self.send_control = topics, client_id, send_control
        self.claim = Claim.mine(topics.gateway_id, client_id)
        self.held_off = False  # a rival was found: the next connect waits RIVAL_WAIT
        self._reported: str | None = None

    def _report(self, text: str) -> None:
        """An error once per rival (the retries after it are quiet)."""
        if text != self._reported:
            log.error("mqtt: %s", text)
            self._reported = text

    async def rival(self, brokers: Sequence[Broker], make: Callable[[str], paho.Client],
                    also: Sequence[str] = ()) -> Probed:
        """Asked before connecting: the first of ``brokers`` to answer, and a live
        gateway holding this ``gateway_id`` or client id there; with the retained
        messages it serves on this gateway's topics and on ``also``.  Raises
        ``BrokerUnreached`` when no broker was reached."""
        probe_id = self.probe_id
        t = self.topics
        try:
            broker, found = await read_retained_hedged(
                make, brokers, probe_id, [t.status, t.instance, t.client(self.client_id), *also])
        except ProbeFailed as failed:  # the real connect goes there, and says why
            return Probed(failed.broker, None, {})
        served = dict(found)
        try:
            rival = live_rival(self.claim, _text(found.get(t.status)),
                               Claim.parse(found.get(t.instance, b"")))
            what = f"gateway_id {t.gateway_id!r}"
            other = Claim.parse(found.get(t.client(self.client_id), b""))
            if rival is None and other is not None and other.gateway_id != t.gateway_id:
                # the client id is claimed by a gateway of another id: is it running?
                theirs = t.of_gateway(other.gateway_id)
                # (a client id of its own: a hedge that lost may still be connecting)
                try:
                    found = await read_retained(make, broker, f"{probe_id}-c",
                                                [theirs.status, theirs.instance])
                except BrokerUnreached as failed:
                    raise BrokerUnreached(failed.kind, failed.detail, broker) from failed
                live = live_rival(self.claim, _text(found.get(theirs.status)),
                                  Claim.parse(found.get(theirs.instance, b"")))
                rival = live if live == other else None
                what = f"the client id {self.client_id!r}"
        except (OSError, TimeoutError, ValueError):
            # refused or half-answered: the real connect tries, and says why
            return Probed(broker, None, {})
        if rival is not None:
            self.held_off = True
            self._report(
                f"{what} is in use on {broker} by another gateway ({rival.describe()}); "
                f"this one stays away so as not to take its session or overwrite its "
                f"retained messages, and looks again every {RIVAL_WAIT:g} s. Give each "
                f"gateway its own gateway_id and client_id (docs/scaling.md)")
        return Probed(broker, rival, served)

    @property
    def probe_id(self) -> str:
        """The client id of this gateway's probes (its own: a probe must not take the
        gateway's session)."""
        return f"{self.client_id}-probe-{self.claim.instance[:8]}"

    @property
    def claim_topics(self) -> tuple[str, str]:
        return self.topics.instance, self.topics.client(self.client_id)

    def claim_it(self) -> None:
        for topic in self.claim_topics:
            self.send_control(Message(topic, self.claim.payload(), CONTROL_QOS, True))

    def seen(self, message: paho.MQTTMessage) -> bool:
        """A claim on this id came in while connected; True when this gateway must
        give way (another instance that started first)."""
        if message.retain:
            return False  # stored before this connection: the probe has judged it
        theirs = Claim.parse(bytes(message.payload))
        if theirs is None or theirs.instance == self.claim.instance:
            return False
        if self.claim.first(theirs):
            log.warning("mqtt: another gateway (%s) claimed gateway_id %r or client id %r "
                        "after this one; this one keeps them and publishes its claim again",
                        theirs.describe(), self.topics.gateway_id, self.client_id)
            self.claim_it()
            return False
        self.held_off = True
        self._report(f"gateway_id {self.topics.gateway_id!r} or client id {self.client_id!r} "
                     f"was claimed by another gateway that started first "
                     f"({theirs.describe()}); this one disconnects and looks again every "
                     f"{RIVAL_WAIT:g} s. Give each gateway its own gateway_id and client_id "
                     f"(docs/scaling.md)")
        return True


def _text(payload: bytes | None) -> str | None:
    return None if payload is None else payload.decode(errors="replace")
