"""The Sparkplug B edge node, sans-IO: messages out for what happens, time as an
argument (ms since the epoch).  The gateway is the edge node (its ``gateway_id``),
each sensor a device.  The rules kept (Sparkplug 3.0):

* **bdSeq** goes up by one (0-255, then 0) with every MQTT connection; the NBIRTH and
  the will (NDEATH) of a connection carry the same.  Kept in ``bdseq_file`` across
  restarts when one is configured, so that a will published late by the broker (a
  gateway killed and restarted) is never taken for the new session's death.
* **seq** is 0 in the NBIRTH and one more (mod 256) in every message after it: DBIRTH,
  DDATA, DDEATH.  NDEATH has none.
* **Births** carry every metric with its name, alias, datatype and (for the measured
  values) an ``engUnit`` property; **data** carry only what changed, by alias, with the
  sample's own timestamp.  A device that goes offline gets a DDEATH; when it answers
  again, a DBIRTH with its values.
* **NCMD** ``Node Control/Rebirth`` = true: all the births again (same bdSeq).
* **DCMD** writes a command metric: the catalogue's command, when commands are allowed.
* **STATE**: with a primary host configured, births wait until its
  ``spBv1.0/STATE/{host}`` says online; when it says offline, the node ends its session
  (NDEATH, disconnect) and is born again once the host is back.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import DecodeError

from ...cache import Snapshot
from ...normalise import field_values
from ..mqtt_topics import Message
from .metrics import DataType, MetricRow, Value
from .payload_pb2 import Payload

log = logging.getLogger("imu_gateway.sparkplug")

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"
DATA_QOS, DEATH_QOS = 0, 1


@dataclass(frozen=True, slots=True)
class Device:
    """One sensor as a Sparkplug device: its id (the sensor's name) and metric rows."""

    name: str
    rows: tuple[MetricRow, ...]


@dataclass(frozen=True, slots=True)
class Write:
    """A DCMD's write of a command metric: run ``command`` on ``device``."""

    device: str
    command: str
    value: Value


@dataclass(frozen=True, slots=True)
class Ignored:
    """A command message not acted on, and why (for the log)."""

    reason: str


class BdSeq:
    """The birth/death sequence number, kept in ``path`` when there is one."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._problem: str | None = None  # the last failure to keep it, said once
        self.value = -1  # the first connection takes 0, or the kept one plus one
        if path is not None:
            with contextlib.suppress(OSError, ValueError):
                self.value = int(path.read_text().strip()) % 256

    def next(self) -> int:
        self.value = (self.value + 1) % 256
        if self.path is not None:
            tmp = self.path.with_name(self.path.name + ".tmp")
            try:
                tmp.write_text(f"{self.value}\n")
                os.replace(tmp, self.path)  # whole or not at all: a crash leaves the old
            except OSError as exc:
                # A full or read-only disk must not cost the session: the number goes
                # on in memory (a restart then starts from the last one kept).
                if str(exc) != self._problem:
                    self._problem = str(exc)
                    log.error("sparkplug: cannot keep bdSeq in %s (%s); going on without "
                              "(a restart would repeat a bdSeq)", self.path, exc)
            else:
                self._problem = None
        return self.value


class EdgeNode:
    """One edge node's Sparkplug messages.  ``connected()`` at each connection gives
    the will; ``birth()`` the births; ``update()`` the data of a snapshot."""

    def __init__(self, group_id: str, node_id: str, devices: Sequence[Device],
                 bdseq: BdSeq) -> None:
        self.group, self.node = group_id, node_id
        self.devices = {d.name: d for d in devices}
        self.bdseq = bdseq
        self.session = 0  # this connection's bdSeq
        self.seq = 0
        self.born = False
        self.alive: set[str] = set()  # devices born and not dead since
        self.last: dict[str, dict[str, Value | None]] = {}  # last values sent, per device
        # aliases: unique in the node, stable for the process
        names = [(None, BDSEQ), (None, REBIRTH),
                 *((d.name, r.name) for d in devices for r in d.rows)]
        self.alias = {key: number for number, key in enumerate(names, start=1)}
        self.by_alias = {number: key for key, number in self.alias.items()}

    # ------------------------------------------------------------ topics

    def topic(self, kind: str, device: str | None = None) -> str:
        base = f"{NAMESPACE}/{self.group}/{kind}/{self.node}"
        return f"{base}/{device}" if device is not None else base

    @staticmethod
    def state_topics(host: str) -> tuple[str, str]:
        """Where a primary host says whether it is online: Sparkplug 3.0's topic, and
        2.2's (outside the namespace)."""
        return f"{NAMESPACE}/STATE/{host}", f"STATE/{host}"

    @property
    def command_topics(self) -> tuple[str, str]:
        return self.topic("NCMD"), f"{NAMESPACE}/{self.group}/DCMD/{self.node}/+"

    # ------------------------------------------------------------ session

    def connected(self) -> Message:
        """A new MQTT connection: its bdSeq, and its will (the NDEATH)."""
        self.session = self.bdseq.next()
        self.born = False
        self.alive.clear()
        return self.death()

    def death(self) -> Message:
        payload = Payload()
        self._metric(payload, BDSEQ, None, DataType.INT64, self.session, named=True)
        return Message(self.topic("NDEATH"), payload.SerializeToString(), DEATH_QOS, False)

    def birth(self, snaps: Iterable[Snapshot], now_ms: int) -> list[Message]:
        """NBIRTH (seq 0), then a DBIRTH for every device that is online."""
        self.seq, self.born = 0, True
        self.alive.clear()
        payload = Payload(timestamp=now_ms, seq=0)
        self._metric(payload, BDSEQ, None, DataType.INT64, self.session, named=True)
        self._metric(payload, REBIRTH, None, DataType.BOOLEAN, False, named=True)
        out = [Message(self.topic("NBIRTH"), payload.SerializeToString(), DATA_QOS, False)]
        for snap in snaps:
            if snap.name in self.devices and snap.online:
                out.append(self._device_birth(snap, now_ms))
        return out

    def update(self, snap: Snapshot, now_ms: int) -> list[Message]:
        """A sensor's new snapshot: DBIRTH, DDATA of what changed, or DDEATH."""
        if not self.born or snap.name not in self.devices:
            return []
        if not snap.online:
            if snap.name not in self.alive:
                return []
            self.alive.discard(snap.name)
            payload = Payload(timestamp=now_ms, seq=self._next_seq())
            return [Message(self.topic("DDEATH", snap.name), payload.SerializeToString(),
                            DATA_QOS, False)]
        if snap.name not in self.alive:
            return [self._device_birth(snap, now_ms)]
        return self._data(snap, now_ms)

    def result(self, device: str, text: str, now_ms: int) -> list[Message]:
        """A command's outcome, as the device's ``Commands/Result``."""
        if not self.born or device not in self.alive:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        self._metric(payload, "Commands/Result", device, DataType.STRING, text)
        return [Message(self.topic("DDATA", device), payload.SerializeToString(),
                        DATA_QOS, False)]

    # ------------------------------------------------------------ incoming

    def command(self, topic: str, data: bytes) -> list[Write] | bool | Ignored:
        """An NCMD or DCMD: True for a rebirth, the writes of a DCMD, or Ignored."""
        try:
            payload = Payload.FromString(data)
        except DecodeError as exc:  # a peer's bad bytes
            return Ignored(f"not a Sparkplug B payload ({exc})")
        if topic == self.topic("NCMD"):
            for m in payload.metrics:
                key = (None, m.name) if m.HasField("name") else self.by_alias.get(m.alias)
                if key == (None, REBIRTH) and m.WhichOneof("value") == "boolean_value" \
                        and m.boolean_value:
                    return True
            return Ignored("an NCMD without Node Control/Rebirth = true")
        device = topic.rsplit("/", 1)[-1]
        if device not in self.devices:
            return Ignored(f"a DCMD for unknown device {device!r}")
        rows = {r.name: r for r in self.devices[device].rows}
        writes = []
        for m in payload.metrics:
            key = (device, m.name) if m.HasField("name") else self.by_alias.get(m.alias)
            row = rows.get(key[1]) if key is not None and key[0] == device else None
            if row is None or row.command is None:
                return Ignored(f"a DCMD for {device} writes {m.name or m.alias!r}, "
                               "which is not a command metric")
            value = _value_of(m, row.datatype)
            if value is None or value is False:
                return Ignored(f"a DCMD for {device} writes {row.name} without a value "
                               "(or false: write true to run a command without arguments)")
            writes.append(Write(device, row.command, value))
        return writes or Ignored(f"a DCMD for {device} without metrics")

    @staticmethod
    def host_online(data: bytes) -> bool | None:
        """A primary host's STATE payload: Sparkplug 3.0's JSON ``{"online": …}``, or
        2.2's plain ``ONLINE``/``OFFLINE``; None for anything else."""
        with contextlib.suppress(ValueError, AttributeError, TypeError):
            online = json.loads(data).get("online")
            return online if isinstance(online, bool) else None
        text = data.strip().upper()
        return {b"ONLINE": True, b"OFFLINE": False}.get(text)

    # ------------------------------------------------------------ the payloads

    def _device_birth(self, snap: Snapshot, now_ms: int) -> Message:
        self.alive.add(snap.name)
        device = self.devices[snap.name]
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        values: dict[str, Value | None] = {}
        fields = _fields(snap)
        for row in device.rows:
            values[row.name] = value = row.of(snap, fields)
            metric = self._metric(payload, row.name, snap.name, row.datatype, value,
                                  named=True, at=_sample_ms(snap, now_ms))
            if row.unit is not None:
                metric.properties.keys.append("engUnit")
                metric.properties.values.add(type=DataType.STRING, string_value=row.unit)
        self.last[snap.name] = values
        return Message(self.topic("DBIRTH", snap.name), payload.SerializeToString(),
                       DATA_QOS, False)

    def _data(self, snap: Snapshot, now_ms: int) -> list[Message]:
        last, fields = self.last[snap.name], _fields(snap)
        now = [(row, row.of(snap, fields)) for row in self.devices[snap.name].rows
               if row.command is None]
        changed = [(row, value) for row, value in now if value != last.get(row.name)]
        if not changed:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        at = _sample_ms(snap, now_ms)
        for row, value in changed:
            last[row.name] = value
            self._metric(payload, row.name, snap.name, row.datatype, value, at=at)
        return [Message(self.topic("DDATA", snap.name), payload.SerializeToString(),
                        DATA_QOS, False)]

    def _metric(self, payload: Payload, metric: str, device: str | None, datatype: DataType,
                value: Value | None, *, named: bool = False,
                at: int | None = None) -> Payload.Metric:
        """Adds one metric: by alias and type, and in births (``named``) by name too.
        (Sparkplug 3.0 says data SHOULD NOT carry the type; Eclipse Tahu's own decoder
        gives no value without it, so it is sent: 2 bytes a metric.)"""
        m = payload.metrics.add()
        if named:
            m.name = metric
        m.datatype = datatype
        m.alias = self.alias[(device, metric)]
        if at is not None:
            m.timestamp = at
        if value is None:
            m.is_null = True
        elif datatype is DataType.BOOLEAN:
            m.boolean_value = bool(value)
        elif datatype is DataType.STRING:
            m.string_value = str(value)
        elif datatype is DataType.FLOAT:
            m.float_value = float(value)
        elif datatype is DataType.DOUBLE:
            m.double_value = float(value)
        elif datatype in (DataType.INT64, DataType.UINT64):
            m.long_value = int(value) & 0xFFFF_FFFF_FFFF_FFFF  # signed: two's complement
        else:
            m.int_value = int(value) & 0xFFFF_FFFF
        return m

    def _next_seq(self) -> int:
        self.seq = (self.seq + 1) % 256
        return self.seq


def _fields(snap: Snapshot) -> dict[str, float]:
    return field_values(snap.reading) if snap.reading is not None else {}


def _sample_ms(snap: Snapshot, now_ms: int) -> int:
    return int(snap.timestamp.timestamp() * 1000) if snap.timestamp is not None else now_ms


def _value_of(metric: Payload.Metric, datatype: DataType) -> Value | None:
    """A written metric's value, as the row's type wants it (None: none, or another
    type's field)."""
    field = metric.WhichOneof("value")
    if field is None or metric.is_null:
        return None
    if datatype is DataType.BOOLEAN:
        return metric.boolean_value if field == "boolean_value" else None
    if datatype is DataType.STRING:
        return metric.string_value if field == "string_value" else None
    if field == "int_value":  # Int32 written as two's complement in a uint32
        v = metric.int_value
        return v - (1 << 32) if datatype is DataType.INT32 and v >= 1 << 31 else v
    if field == "long_value":
        return metric.long_value
    if field in ("float_value", "double_value"):
        number: float = getattr(metric, field)
        return int(number) if datatype is DataType.INT32 and number.is_integer() else number
    return None
