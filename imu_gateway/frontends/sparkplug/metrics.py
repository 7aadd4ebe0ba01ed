"""What a Sparkplug B device (one sensor) and the edge node (the gateway) carry: one
row per metric.  The births, the data and docs/sparkplug.md all come from these rows.

A sensor's metrics are its series' measured values and those derived from them
(``model.VALUE_GROUPS``: one folder per group, the value's unit as its ``engUnit``
property; Double, so a sensor's 32.52 is 32.52 in the host, not a float32's
widening), a few status and identity metrics, and, when commands are allowed, one
metric per command of the catalogue the series and protocol have
(``commands.CATALOGUE``); and each of its alarms' state (``ALARM_ROWS``:
``Alarms/{alarm}/…``, from the gateway's alarms, docs/alarms.md).  The edge node's
own metrics are each bus's counters (``BUS_ROWS``: ``Buses/{bus}/…``, from ``Gateway.stats()``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from ...alarms import AlarmState
from ...cache import Snapshot, Status
from ...commands import CATALOGUE, CommandSpec, argument_type, commands_for
from ...config import SensorConfig
from ...model import CAPABILITIES, VALUE_GROUPS, Series, WireProtocol
from ...stats import ERROR_KINDS, BusStats

Value = float | int | bool | str


class DataType(enum.IntEnum):
    """Sparkplug B's data type numbers (those used here)."""

    INT32 = 3
    INT64 = 4
    UINT8 = 5
    UINT32 = 7
    UINT64 = 8
    FLOAT = 9
    DOUBLE = 10
    BOOLEAN = 11
    STRING = 12

    @property
    def spelled(self) -> str:
        """As Sparkplug writes it: ``UInt64``, ``Boolean``."""
        return self.name.title().replace("Uint", "UInt")


#: The datatype of every measured and derived value.
VALUE_TYPE = DataType.DOUBLE


@dataclass(frozen=True, slots=True)
class MetricRow:
    """One metric: its name (``/`` makes folders), type, unit, what it says, and its
    value in a snapshot (``None``: no value now; it is sent as null)."""

    name: str
    datatype: DataType
    description: str
    value: Callable[[Snapshot], Value | None]
    unit: str | None = None
    command: str | None = None  # a DCMD writes it: this command of the catalogue
    field: str | None = None  # a measured value: this field of the reading

    def of(self, snap: Snapshot, fields: Mapping[str, float]) -> Value | None:
        """The value now; ``fields``: the snapshot's reading by field, worked out once
        for all the rows (a reading has 19 values, and a row each).  A value that is not
        a finite number (a derived value that has none now, a Modbus float register's
        NaN) is no value: null."""
        if self.field is None:
            return self.value(snap)
        value = fields.get(self.field)
        return value if value is not None and math.isfinite(value) else None


def value_rows(series: Series) -> list[MetricRow]:
    """The measured and derived values of ``series``: ``{Group title}/{field}``."""
    return [MetricRow(f"{spec.title}/{name}", VALUE_TYPE, f"{name} ({spec.name})",
                      lambda s: None, spec.symbol or None, field=name)
            for group, spec in VALUE_GROUPS.items() if group in CAPABILITIES[series].groups
            for name in spec.fields]


STATUS_ROWS = (
    MetricRow("Status/Stale", DataType.BOOLEAN,
              "the latest sample is older than the sensor's stale_after_ms",
              lambda s: s.status is Status.STALE),
    MetricRow("Status/Sequence", DataType.UINT64,
              "the sample's sequence number (one more per new reading)", lambda s: s.seq),
    MetricRow("Status/Errors", DataType.UINT64,
              "the sensor's errors so far (timeouts, bad checksums, bad frames)",
              lambda s: s.errors),
    MetricRow("Status/Busy", DataType.BOOLEAN, "a save or calibration is running",
              lambda s: s.busy),
)

#: After each command written as a DCMD: its outcome, ``{command}: ok`` or
#: ``{command}: {kind}: {message}``.
RESULT = MetricRow("Commands/Result", DataType.STRING,
                   "the outcome of the last command written as a DCMD", lambda s: None)


def identity_rows(sensor: SensorConfig, protocol: WireProtocol) -> list[MetricRow]:
    return [
        MetricRow("Properties/Series", DataType.STRING, "IMU, VG, AH or MINS",
                  lambda s: sensor.series.name),
        MetricRow("Properties/Protocol", DataType.STRING, "native or modbus",
                  lambda s: protocol.name.lower()),
        MetricRow("Properties/Address", DataType.UINT32, "the sensor's address on its bus",
                  lambda s: sensor.address),
    ]


def command_type(spec: CommandSpec) -> DataType:
    """A command's metric type: Boolean (write true) without an argument, else its
    argument's type."""
    kind = argument_type(spec)
    return DataType.BOOLEAN if kind is None else {
        str: DataType.STRING, int: DataType.INT32}.get(kind, DataType.DOUBLE)


def command_rows(series: Series, protocol: WireProtocol) -> list[MetricRow]:
    have = commands_for(series, protocol)
    rows = [MetricRow(f"Commands/{spec.name}", command_type(spec), spec.summary,
                      lambda s: None, command=spec.name)
            for spec in CATALOGUE.values() if spec.name in have]
    return [*rows, RESULT]


def device_rows(sensor: SensorConfig, protocol: WireProtocol,
                commands: bool) -> list[MetricRow]:
    """Every metric of one sensor's device, in birth order."""
    rows = [*value_rows(sensor.series), *STATUS_ROWS, *identity_rows(sensor, protocol)]
    return [*rows, *command_rows(sensor.series, protocol)] if commands else rows


@dataclass(frozen=True, slots=True)
class AlarmMetric:
    """One metric of every alarm of a sensor: ``Alarms/{alarm}/{name}``, its value in
    the alarm's state.  ``acknowledges``: a DCMD writing true to it acknowledges."""

    name: str
    datatype: DataType
    description: str
    value: Callable[[AlarmState], Value]
    acknowledges: bool = False

    def metric(self, alarm: str) -> str:
        return f"Alarms/{alarm}/{self.name}"


ALARM_ROWS = (
    AlarmMetric("Active", DataType.BOOLEAN,
                "true while the alarm is active (beyond its limit after the on-delay, or "
                "held by its latch)", lambda a: a.active),
    AlarmMetric("Acked", DataType.BOOLEAN,
                "false while the alarm waits for an acknowledgement; a DCMD writing true "
                "acknowledges it (with `allow_commands`)", lambda a: a.acked,
                acknowledges=True),
    AlarmMetric("State", DataType.STRING,
                "the ISA-18.2 state: `normal`, `active_unacked`, `active_acked`, "
                "`rtn_unacked`", lambda a: a.state.value),
    AlarmMetric("Severity", DataType.STRING, "`info`, `warning` or `critical` (as configured; "
                "`critical` for the communication alarm)", lambda a: a.severity.value),
)


@dataclass(frozen=True, slots=True)
class BusRow:
    """One node metric of every bus: ``Buses/{bus}/{name}``, its value in the bus's
    stats."""

    name: str
    datatype: DataType
    description: str
    value: Callable[[BusStats], Value]

    def metric(self, bus: str) -> str:
        return f"Buses/{bus}/{self.name}"


def _errors_of(kind: str) -> Callable[[BusStats], Value]:
    return lambda b: b.errors.get(kind, 0)


BUS_ROWS = (
    BusRow("Transactions", DataType.UINT64, "exchanges done", lambda b: b.transactions),
    BusRow("Errors/all", DataType.UINT64, "failed exchanges of every kind",
           lambda b: sum(b.errors.values())),
    *(BusRow(f"Errors/{kind}", DataType.UINT64, f"failed exchanges: {kind}",
             _errors_of(kind)) for kind in ERROR_KINDS),
    BusRow("TransactionsPerSecond", DataType.DOUBLE, "exchanges per second, over the last 5 s",
           lambda b: b.transactions_per_s),
    BusRow("Utilisation", DataType.DOUBLE, "time in exchanges ÷ elapsed (0-1)",
           lambda b: b.utilisation),
    BusRow("QueueDepth", DataType.UINT32, "commands and reads waiting", lambda b: b.queue_depth),
    BusRow("PortOpen", DataType.BOOLEAN, "the serial port is open", lambda b: b.port_open),
)
