"""The Sparkplug B edge node, sans-IO: messages out for what happens, time as an
argument (ms since the epoch).  The gateway is the edge node (its ``gateway_id``),
each sensor a device.  The rules kept (Sparkplug 3.0):

* **bdSeq** goes up by one (0-255, then 0) with every MQTT CONNECT packet sent (the
  will in it carries the number): a try that never sent one (the broker refused the
  TCP connection) takes none.  The NBIRTH and the will (NDEATH) of a connection carry
  the same.  Kept in ``bdseq_file`` across restarts when one is configured, so that a
  will published late by the broker (a gateway killed and restarted) is never taken
  for the new session's death.
* **seq** is 0 in the NBIRTH and one more (mod 256) in every message after it: DBIRTH,
  DDATA, DDEATH, NDATA.  NDEATH has none.
* **Births** carry every metric with its name, alias, datatype and (for the measured
  values) an ``engUnit`` property; **data** carry only what changed, by alias.  Every
  metric has a timestamp: a sensor's, its sample's; the node's and a command's
  result, the time they are sent.  The NBIRTH and NDATA carry each bus's counters.  A
  device that goes offline gets a DDEATH; when it answers again, a DBIRTH with its
  values.
* **NCMD** ``Node Control/Rebirth`` = true: all the births again (same bdSeq).
* **A reload** that changes the sensors (``set_devices``): a DDEATH for each device
  born and gone, then all the births again, as for a Rebirth (same bdSeq, same MQTT
  session).  A metric kept keeps its alias; a new one takes a number never used.
* **DCMD** writes a command metric: the catalogue's command, when commands are allowed;
  a write refused here (not a command, the wrong type, no value) is answered in
  ``Commands/Result`` like a command the sensor refused.
* **Alarms**: each alarm of a device is ``Alarms/{alarm}/…`` (``ALARM_ROWS``), in its
  DBIRTH with the state the alarm has then, and in a DDATA of its own at each
  transition (the cache's ``ALARM`` event), stamped with the transition's time: one
  DDATA per transition, so that none is merged into another or lost with a reading
  that changed nothing else.  A transition of a device that is not born (offline: its
  DDEATH said so) is in its next DBIRTH.  A DCMD writing true to
  ``Alarms/{alarm}/Acked`` acknowledges the alarm (``Acknowledge``), answered in
  ``Commands/Result`` as a command is.
* **STATE** (``host``): with a primary host configured, births wait until it says
  online; when it says offline, the node ends its session (NDEATH, disconnect) and is
  born again once the host is back.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import DecodeError

from ...alarms import AlarmEvent, AlarmState
from ...cache import Snapshot
from ...derived import values_of
from ...errors import ErrorKind
from ...mqtt_link.message import Message
from ...stats import BusStats
from .metrics import ALARM_ROWS, BUS_ROWS, RESULT, DataType, MetricRow, Value
from .payload_pb2 import Payload

log = logging.getLogger("imu_gateway.sparkplug")

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"
DATA_QOS, DEATH_QOS = 0, 1


@dataclass(frozen=True, slots=True)
class Device:
    """One sensor as a Sparkplug device: its id (the sensor's name), metric rows and
    alarms (by name, in the gateway's order: the communication alarm last)."""

    name: str
    rows: tuple[MetricRow, ...]
    alarms: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Write:
    """A DCMD's write of a command metric: run ``command`` on ``device``."""

    device: str
    command: str
    value: Value


@dataclass(frozen=True, slots=True)
class Acknowledge:
    """A DCMD's write of true to ``Alarms/{alarm}/Acked``: acknowledge the alarm."""

    device: str
    alarm: str
    metric: str  # the metric written (its outcome is reported under this name)


@dataclass(frozen=True, slots=True)
class Refused:
    """A DCMD's write not run, and why: answered in the device's ``Commands/Result``."""

    device: str
    metric: str  # the command, or the metric written when it is none
    kind: ErrorKind
    reason: str

    @property
    def text(self) -> str:
        return f"{self.metric}: {self.kind.value}: {self.reason}"


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

    @property
    def upcoming(self) -> int:
        """The number the next CONNECT carries (``next()`` takes it once sent)."""
        return (self.value + 1) % 256

    def next(self) -> int:
        self.value = self.upcoming
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
                 bdseq: BdSeq, buses: Sequence[str] = ()) -> None:
        self.group, self.node = group_id, node_id
        self.devices = {d.name: d for d in devices}
        self.bdseq = bdseq
        self.session = 0  # this connection's bdSeq
        self.seq = 0
        self.born = False
        self.alive: set[str] = set()  # devices born and not dead since
        self.last: dict[str, dict[str, Value | None]] = {}  # last values sent, per device
        self.last_node: dict[str, Value] = {}  # the node metrics' last values sent
        self.alias: dict[tuple[str | None, str], int] = {}
        self._aliases = 0  # the aliases given so far (the last number used)
        # each alarm's latest state, by (device, alarm): the births carry it
        self.alarms: dict[tuple[str, str], AlarmState] = {}
        self._set_devices(devices, buses)

    def _set_devices(self, devices: Sequence[Device], buses: Sequence[str]) -> None:
        """The devices and buses, and their metrics' aliases (``_aliases``)."""
        self.devices = {d.name: d for d in devices}
        self.alias, self._aliases = _aliases(_metric_keys(devices, buses), self.alias,
                                             self._aliases)
        self.by_alias = {number: key for key, number in self.alias.items()}
        self._acks = {(d.name, r.metric(a)): a for d in devices for a in d.alarms
                      for r in ALARM_ROWS if r.acknowledges}

    def set_devices(self, devices: Sequence[Device], buses: Sequence[str],
                    now_ms: int) -> list[Message]:
        """A reload changed the sensors: a DDEATH for each device born and gone (none
        while the node is not born); the rebirth that follows is the caller's."""
        out = []
        for name in sorted(self.alive - {d.name for d in devices}):
            if self.born:
                payload = Payload(timestamp=now_ms, seq=self._next_seq())
                out.append(Message(self.topic("DDEATH", name), payload.SerializeToString(),
                                   DATA_QOS, False))
            self.alive.discard(name)
            self.last.pop(name, None)
        self._set_devices(devices, buses)
        self.alarms = {k: state for k, state in self.alarms.items() if k[0] in self.devices}
        return out

    # ------------------------------------------------------------ topics

    def topic(self, kind: str, device: str | None = None) -> str:
        base = f"{NAMESPACE}/{self.group}/{kind}/{self.node}"
        return f"{base}/{device}" if device is not None else base

    @property
    def command_topics(self) -> tuple[str, str]:
        return self.topic("NCMD"), f"{NAMESPACE}/{self.group}/DCMD/{self.node}/+"

    # ------------------------------------------------------------ session

    def will(self, now_ms: int) -> Message:
        """The will (the NDEATH) of the next connection try, with the bdSeq its CONNECT
        carries; ``connect_sent()`` takes the number once that CONNECT went out."""
        self.session = self.bdseq.upcoming
        self.born = False
        self.alive.clear()
        return self.death(now_ms)

    def connect_sent(self) -> None:
        """The CONNECT with the last will went out: its bdSeq is spent."""
        self.session = self.bdseq.next()

    def death(self, now_ms: int) -> Message:
        payload = Payload(timestamp=now_ms)
        self._metric(payload, BDSEQ, None, DataType.INT64, self.session, now_ms, named=True)
        return Message(self.topic("NDEATH"), payload.SerializeToString(), DEATH_QOS, False)

    def birth(self, snaps: Iterable[Snapshot], buses: Iterable[BusStats],
              now_ms: int, alarms: Iterable[AlarmState] = ()) -> list[Message]:
        """NBIRTH (seq 0, with the buses' counters), then a DBIRTH for every device that
        is online, with ``alarms``, every alarm's state now."""
        for state in alarms:
            self.alarms[state.sensor, state.name] = state
        self.seq, self.born = 0, True
        self.alive.clear()
        payload = Payload(timestamp=now_ms, seq=0)
        self._metric(payload, BDSEQ, None, DataType.INT64, self.session, now_ms, named=True)
        self._metric(payload, REBIRTH, None, DataType.BOOLEAN, False, now_ms, named=True)
        self.last_node = {}
        for name, datatype, value in self._node_values(buses):
            self.last_node[name] = value
            self._metric(payload, name, None, datatype, value, now_ms, named=True)
        out = [Message(self.topic("NBIRTH"), payload.SerializeToString(), DATA_QOS, False)]
        for snap in snaps:
            if snap.name in self.devices and snap.online:
                out.append(self._device_birth(snap, now_ms))
        return out

    def node_data(self, buses: Iterable[BusStats], now_ms: int) -> list[Message]:
        """An NDATA of the node metrics that changed since last sent (none: nothing)."""
        if not self.born:
            return []
        changed = [(name, datatype, value) for name, datatype, value in self._node_values(buses)
                   if self.last_node.get(name) != value]
        if not changed:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        for name, datatype, value in changed:
            self.last_node[name] = value
            self._metric(payload, name, None, datatype, value, now_ms)
        return [Message(self.topic("NDATA"), payload.SerializeToString(), DATA_QOS, False)]

    def _node_values(self, buses: Iterable[BusStats]) -> list[tuple[str, DataType, Value]]:
        """The node metrics now: each known bus's counters (a bus the births did not
        name has no alias, and is left out)."""
        return [(row.metric(bus.name), row.datatype, row.value(bus))
                for bus in buses for row in BUS_ROWS
                if (None, row.metric(bus.name)) in self.alias]

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

    def alarm(self, event: AlarmEvent, now_ms: int) -> list[Message]:
        """An alarm's transition: a DDATA of its metrics that changed, stamped with the
        transition's time (none when the device is not born: its next DBIRTH has the
        state; nor when its DBIRTH has it already)."""
        state = event.state
        self.alarms[state.sensor, state.name] = state
        device = state.sensor
        if not self.born or device not in self.alive or \
                state.name not in self.devices[device].alarms:
            return []
        last = self.last[device]
        changed = [(row, row.value(state)) for row in ALARM_ROWS
                   if row.value(state) != last.get(row.metric(state.name))]
        if not changed:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        at = int(event.transition.at * 1000)
        for row, value in changed:
            last[row.metric(state.name)] = value
            self._metric(payload, row.metric(state.name), device, row.datatype, value, at)
        return [Message(self.topic("DDATA", device), payload.SerializeToString(),
                        DATA_QOS, False)]

    def result(self, device: str, text: str, now_ms: int) -> list[Message]:
        """A command's outcome, as the device's ``Commands/Result``."""
        if not self.born or device not in self.alive:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        self._metric(payload, RESULT.name, device, DataType.STRING, text, now_ms)
        return [Message(self.topic("DDATA", device), payload.SerializeToString(),
                        DATA_QOS, False)]

    # ------------------------------------------------------------ incoming

    def command(self, topic: str, data: bytes
                ) -> list[Write | Acknowledge | Refused] | bool | Ignored:
        """An NCMD or DCMD: True for a rebirth, a DCMD's writes (each run, or refused
        with its reason), or Ignored."""
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
        writes = [self._write(device, m) for m in payload.metrics]
        if not writes:
            return Ignored(f"a DCMD for {device} without metrics")
        if RESULT not in self.devices[device].rows:  # commands not allowed: nowhere to answer
            refused = next((w for w in writes if isinstance(w, Refused)), None)
            if refused is not None:
                return Ignored(f"a DCMD for {device}: {refused.text}")
        return writes

    def _write(self, device: str, m: Payload.Metric) -> Write | Acknowledge | Refused:
        """One metric of a DCMD: the command it runs, the alarm it acknowledges, or why
        it does neither."""
        rows = {r.name: r for r in self.devices[device].rows}
        key = (device, m.name) if m.HasField("name") else self.by_alias.get(m.alias)
        if key is not None and key[0] == device and key in self._acks:
            return _acknowledge(device, key[1], self._acks[key], m)
        row = rows.get(key[1]) if key is not None and key[0] == device else None
        if row is None or row.command is None:
            written = m.name if m.HasField("name") else f"alias {m.alias}"
            return Refused(device, written, ErrorKind.UNKNOWN_COMMAND,
                           "not a command metric (write one of Commands/…, or true to "
                           "Alarms/{alarm}/Acked)")
        value = _value_of(m, row.datatype)
        if m.is_null or m.WhichOneof("value") is None:
            return Refused(device, row.command, ErrorKind.BAD_ARGUMENTS,
                           f"no value written ({row.name} is {row.datatype.spelled})")
        if value is None:
            return Refused(device, row.command, ErrorKind.BAD_ARGUMENTS,
                           f"{row.name} is {row.datatype.spelled}; the DCMD wrote "
                           f"{_written_type(m)}")
        if value is False:
            return Refused(device, row.command, ErrorKind.BAD_ARGUMENTS,
                           "false written: write true to run a command without arguments")
        return Write(device, row.command, value)

    # ------------------------------------------------------------ the payloads

    def _device_birth(self, snap: Snapshot, now_ms: int) -> Message:
        self.alive.add(snap.name)
        device = self.devices[snap.name]
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        values: dict[str, Value | None] = {}
        fields = values_of(snap)  # worked out once per sample, for every front end
        for row in device.rows:
            values[row.name] = value = row.of(snap, fields)
            metric = self._metric(payload, row.name, snap.name, row.datatype, value,
                                  _sample_ms(snap, now_ms), named=True)
            if row.unit is not None:
                metric.properties.keys.append("engUnit")
                metric.properties.values.add(type=DataType.STRING, string_value=row.unit)
        for alarm in device.alarms:
            self._alarm_birth(payload, device.name, alarm, values, now_ms)
        self.last[snap.name] = values
        return Message(self.topic("DBIRTH", snap.name), payload.SerializeToString(),
                       DATA_QOS, False)

    def _alarm_birth(self, payload: Payload, device: str, alarm: str,
                     values: dict[str, Value | None], now_ms: int) -> None:
        """An alarm's metrics in its device's DBIRTH, stamped with its latest
        transition's time (no transition yet: the birth's)."""
        state = self.alarms.get((device, alarm))
        if state is None:  # (not told yet: a birth before the gateway's states)
            return
        at = int(state.since * 1000) if state.since is not None else now_ms
        for row in ALARM_ROWS:
            values[row.metric(alarm)] = value = row.value(state)
            self._metric(payload, row.metric(alarm), device, row.datatype, value, at,
                         named=True)

    def _data(self, snap: Snapshot, now_ms: int) -> list[Message]:
        last, fields = self.last[snap.name], values_of(snap)
        now = [(row, row.of(snap, fields)) for row in self.devices[snap.name].rows
               if row.command is None]
        changed = [(row, value) for row, value in now if value != last.get(row.name)]
        if not changed:
            return []
        payload = Payload(timestamp=now_ms, seq=self._next_seq())
        at = _sample_ms(snap, now_ms)
        for row, value in changed:
            last[row.name] = value
            self._metric(payload, row.name, snap.name, row.datatype, value, at)
        return [Message(self.topic("DDATA", snap.name), payload.SerializeToString(),
                        DATA_QOS, False)]

    def _metric(self, payload: Payload, metric: str, device: str | None, datatype: DataType,
                value: Value | None, at: int, *, named: bool = False) -> Payload.Metric:
        """Adds one metric: by alias, type and timestamp (``at``, ms), and in births
        (``named``) by name too.
        (Sparkplug 3.0 says data SHOULD NOT carry the type; Eclipse Tahu's own decoder
        gives no value without it, so it is sent: 2 bytes a metric.)"""
        m = payload.metrics.add()
        if named:
            m.name = metric
        m.datatype = datatype
        m.alias = self.alias[(device, metric)]
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


def _metric_keys(devices: Sequence[Device], buses: Sequence[str]
                 ) -> list[tuple[str | None, str]]:
    """Every metric of the node, as (device or None, metric name)."""
    return [(None, BDSEQ), (None, REBIRTH),
            *((None, r.metric(bus)) for bus in buses for r in BUS_ROWS),
            *((d.name, r.name) for d in devices for r in d.rows),
            *((d.name, r.metric(a)) for d in devices for a in d.alarms for r in ALARM_ROWS)]


def _aliases(names: Sequence[tuple[str | None, str]], kept: dict[tuple[str | None, str], int],
             last: int) -> tuple[dict[tuple[str | None, str], int], int]:
    """The alias of each metric of ``names``: unique in the node and stable for the
    process (a metric kept across a reload keeps its ``kept`` one; a new one takes the
    next number after ``last``, never used before); with the new last."""
    alias = {}
    for key in names:
        if key not in kept:
            last += 1
        alias[key] = kept.get(key, last)
    return alias, last


def _acknowledge(device: str, metric: str, alarm: str,
                 m: Payload.Metric) -> Acknowledge | Refused:
    """A write to an alarm's ``Acked``: true acknowledges; anything else is refused."""
    if _value_of(m, DataType.BOOLEAN) is True:
        return Acknowledge(device, alarm, metric)
    written = "false" if _value_of(m, DataType.BOOLEAN) is False else \
        "no value" if m.is_null or m.WhichOneof("value") is None else _written_type(m)
    return Refused(device, metric, ErrorKind.BAD_ARGUMENTS,
                   f"{metric} is Boolean: write true to acknowledge (the DCMD wrote "
                   f"{written})")


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


def _written_type(metric: Payload.Metric) -> str:
    """What a written metric says it is: its datatype, or the field its value is in."""
    with contextlib.suppress(ValueError):
        return f"a {DataType(metric.datatype).spelled}"
    field = metric.WhichOneof("value") or "no"
    return f"a {field.removesuffix('_value')} value"
