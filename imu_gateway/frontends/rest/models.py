"""The REST API's response models (they make the OpenAPI document)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...model import VALUE_GROUPS, Group

# ------------------------------------------------------------------ response models


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorOut(BaseModel):
    """Every error: what went wrong and its kind.  A command's failure also carries the
    command result's other fields (``ok``, ``sensor``, ``command``, ``answer``)."""

    model_config = ConfigDict(extra="allow")
    error: str
    kind: str


class AnglesOut(_Out):
    # None: the sensor sent something that is not a number (a Modbus float can be NaN)
    pitch: float | None
    roll: float | None
    yaw: float | None


class VectorOut(_Out):
    x: float | None
    y: float | None
    z: float | None


class QuaternionOut(_Out):
    q0: float | None
    q1: float | None
    q2: float | None
    q3: float | None


class TiltOut(_Out):
    tilt: float | None = Field(description="from vertical, 0-180°")
    tilt_direction: float | None = Field(
        description="the azimuth of the lean in the sensor's frame, 0-360° (0 toward +x, "
        "90 toward +y); null where the tilt is 0")


class VibrationOut(_Out):
    vibration: float | None = Field(
        description="RMS of the acceleration magnitude's deviation from its mean over the "
        "last second; null while that second holds fewer than 10 samples")


_GROUPS = tuple(g.value for g in Group)


def _groups_never_null(schema: dict[str, Any]) -> None:
    """A value group is absent when not measured, never null: say so in the schema
    (the Python type keeps ``None`` as the default for "absent", which is never sent)."""
    for name in _GROUPS:
        prop = schema["properties"][name]
        prop.pop("default", None)
        choices = prop.pop("anyOf")
        prop.update(next(c for c in choices if c.get("type") != "null"))


class ReadingOut(_Out):
    """The reading JSON (as on MQTT); groups the series does not measure are absent.
    ``tilt`` and ``vibration`` are derived from the measured values (docs/alarms.md)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_groups_never_null)
    sensor: str
    ts: str | None = Field(description="when the sample arrived, UTC")
    seq: int
    status: Literal["ok", "stale", "offline"]
    angles: AnglesOut | None = Field(None, description=VALUE_GROUPS[Group.ANGLES].name)
    accel: VectorOut | None = Field(None, description=VALUE_GROUPS[Group.ACCEL].name)
    gyro: VectorOut | None = Field(None, description=VALUE_GROUPS[Group.GYRO].name)
    mag: VectorOut | None = Field(None, description=VALUE_GROUPS[Group.MAG].name)
    quaternion: QuaternionOut | None = Field(
        None, description=VALUE_GROUPS[Group.QUATERNION].name)
    tilt: TiltOut | None = Field(None, description=VALUE_GROUPS[Group.TILT].name)
    vibration: VibrationOut | None = Field(
        None, description=VALUE_GROUPS[Group.VIBRATION].name)


class GroupOut(_Out):
    """A value group of the reading JSON: its fields and how its values are told."""

    group: str = Field(description="the group's key in the reading JSON")
    fields: list[str] = Field(description="its fields, as in per-field topics and registers")
    members: list[str] = Field(description="each field's key within the group's object in "
                               "the reading JSON (accel_x: x), in the same order")
    unit: str = Field(description="the unit's symbol (empty: none)")
    unit_name: str = Field(description="the unit in words")
    digits: int = Field(description="decimals of the sensors' resolution")
    derived_from: list[str] = Field(description="the groups it is worked out from (empty: "
                                    "measured by the sensor)")


class SensorOut(_Out):
    name: str
    bus: str
    series: str
    protocol: str
    address: int
    unit_id: int
    status: Literal["ok", "stale", "offline"]
    online: bool
    busy: bool
    streaming: bool
    seq: int
    ts: str | None = Field(description="the wall time of the latest reading (null: none yet)")
    age_ms: float | None
    achieved_hz: float
    requested_hz: float = Field(description="what the config asks: stream_hz or poll_hz")
    errors: int
    commands: list[str] = Field(description=(
        "the catalogue's commands this sensor has (its series and protocol)"))


class SensorDetailOut(SensorOut):
    config: dict[str, Any]
    settings: dict[str, Any] = Field(description=(
        "what the gateway learnt from commands (and Modbus pass-through); busy_with only "
        "while a save or calibration runs; forgotten (unknown) while the sensor is offline "
        "or its port lost, and read again by the bus when it answers"))
    stats: dict[str, Any]
    reading: ReadingOut | None


class TimingOut(_Out):
    latency_ms: float | None = Field(description="smoothed answer latency: the sensor's "
                                     "turnaround plus the adapter's; null before an answer")
    latency_dev_ms: float | None = Field(description="its mean deviation")
    timeout_ms: float = Field(description="what the next attempt waits beyond the wire time")
    late_answers: int
    early_answers: int = Field(description="answers sooner than request, RTU gap and answer "
                               "could cross the wire, and used")
    requested_hz: float = Field(description="the configured rate: stream_hz while it "
                                "streams, else poll_hz (0: polled flat out)")
    achieved_hz: float = Field(description="readings a second, lately")


class BusOut(_Out):
    name: str
    port: str
    baudrate: int
    protocol: str
    port_open: bool
    transactions: int
    errors: dict[str, int]
    transactions_per_s: float
    utilisation: float = Field(description="time in exchanges ÷ elapsed time")
    wire_utilisation: float
    busy_ms: int
    queue_depth: int
    late_answers: int = Field(description="answers that came after their timeout, and "
                              "were used")
    early_answers: int = Field(description="answers sooner than request, RTU gap and "
                               "answer could cross the wire, and used")
    late_writes: int = Field(description="requests written too late, next to a "
                             "streaming sensor, for their exchange to end before its next "
                             "frame (the bus thread held by a busy machine): each may have "
                             "met that frame")
    sensors: list[str]
    timing: dict[str, TimingOut] = Field(description="each sensor's learned answer timing")


class HealthOut(_Out):
    status: Literal["ok", "degraded"] = Field(
        description="degraded: a port is closed or a sensor is offline")
    gateway_id: str
    version: str
    uptime_s: float
    buses: dict[str, bool] = Field(description="bus name -> port open")
    sensors: dict[str, int] = Field(description="how many sensors are ok, stale, offline")
    interfaces: list[str]
    capture: bool = Field(description=(
        "event capture is on (a `capture:` section): `GET /api/v1/captures` lists them"))
    # int | bool, not float: a count is a whole number (``"clients": 0``, not 0.0) and
    # ``connected`` stays true/false.
    frontends: dict[str, dict[str, int | bool]] = Field(description=(
        "front end -> its counters (whole numbers; `connected` is true/false): clients, "
        "requests, restarts (after a failure) and those of docs/reliability.md"))


class CommandOut(_Out):
    ok: bool
    sensor: str
    command: str
    answer: dict[str, Any]
    error: str | None
    kind: str | None


class EndpointOut(_Out):
    method: str
    path: str
    summary: str


class ApiIndexOut(_Out):
    name: str
    version: str
    docs: str = Field(description="the interactive API reference (Swagger UI)")
    openapi: str = Field(description="the OpenAPI document")
    endpoints: list[EndpointOut]


class ColumnsOut(_Out):
    min: list[float | None]
    max: list[float | None]
    last: list[float | None]


class HistoryOut(_Out):
    sensor: str
    seconds: float
    bucket_s: int = Field(description="the width of a bucket, seconds")
    t: list[int] = Field(description="each bucket's start, Unix seconds, oldest first")
    fields: dict[str, ColumnsOut] = Field(description=(
        "per measured field, its lowest, highest and last value in each bucket (null: "
        "no finite value in that second)"))


_STATES = Literal["normal", "active_unacked", "active_acked", "rtn_unacked"]
_SEVERITIES = Literal["info", "warning", "critical"]


class AlarmOut(_Out):
    """An alarm and its state (docs/alarms.md)."""

    sensor: str
    alarm: str
    field: str | None = Field(description="the field it watches; null: the communication "
                                          "alarm")
    severity: _SEVERITIES
    state: _STATES = Field(description="ISA-18.2's state")
    active: bool
    acked: bool
    value: float | None = Field(description="the value of its latest transition")
    limit: float | None = Field(description="the limit that value was judged by")
    since: str | None = Field(description="the time of its latest transition (UTC); null: "
                                          "none since start")
    latch: bool


class TransitionOut(_Out):
    """One change of an alarm's state, as the journal keeps it."""

    sensor: str
    alarm: str
    ts: str = Field(description="when (UTC)")
    from_: _STATES = Field(alias="from")
    to: _STATES
    value: float | None = Field(description="the value that caused it; null for an "
                                            "acknowledgement and the communication alarm")
    limit: float | None
    severity: _SEVERITIES
    by: str | None = Field(description="who acknowledged (an acknowledgement only)")
