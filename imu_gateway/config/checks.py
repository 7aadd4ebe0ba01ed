"""The checks across keys (a name or an address used twice, a stream rate the protocol
does not offer, two streaming sensors on one bus), run on views that hold plain values:
the schema runs them on every config it validates, and loading on what is valid of a
config that failed (``problems.salvage``).  This module imports no model, so the schema
imports it without a loop."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..model import WireProtocol
from .fields import (
    ADDRESS_RANGE,
    DEFAULT_ADDRESS,
    MODBUS_STREAM_INTERVAL_MS,
    NATIVE_STREAM_HZ,
    protocol_name,
    protocol_or_none,
    show,
    show_number,
)


@dataclass(frozen=True, slots=True)
class SensorView:
    """A sensor for the cross-field checks: each value ``None`` when absent or invalid."""

    path: str
    name: str | None
    address: int | None
    unit_id: int | None
    raw_unit_id: int | None
    stream_hz: float | None


@dataclass(frozen=True, slots=True)
class BusView:
    """A bus for the cross-field checks: each value ``None`` when absent or invalid."""

    path: str
    name: str | None
    port: str | None
    protocol: WireProtocol | None
    sensors: list[SensorView]


def _stream_problem(protocol: WireProtocol, hz: float) -> str | None:
    if hz == 0:
        return None
    if protocol is WireProtocol.NATIVE:
        if hz not in NATIVE_STREAM_HZ:
            rates = ", ".join(map(str, NATIVE_STREAM_HZ))
            return f"must be 0 or one of {rates} on a native bus, not {show_number(hz)}"
        return None
    low, high = MODBUS_STREAM_INTERVAL_MS
    if not low <= round(1000 / hz) <= high:
        return (
            f"on a modbus bus the output interval round(1000/stream_hz) must be "
            f"{low}-{high} ms (stream_hz about 0.016-100), not {show_number(hz)}"
        )
    return None


def cross_problems(buses: list[BusView]) -> list[str]:
    """Every problem that spans fields: uniqueness, per-protocol ranges, streaming."""
    problems: list[str] = []

    def claim(seen: dict[Any, str], key: Any, owner: str, at: str, shown: str) -> None:
        if key in seen:
            problems.append(f"{at}: {shown} is already used by {seen[key]}")
        else:
            seen[key] = owner

    bus_names: dict[str, str] = {}
    ports: dict[str, str] = {}
    sensor_names: dict[str, str] = {}
    unit_ids: dict[int, str] = {}
    for bus in buses:
        if bus.name is not None:
            claim(bus_names, bus.name, bus.path, f"{bus.path}.name", show(bus.name))
        if bus.port is not None:
            claim(ports, bus.port, bus.path, f"{bus.path}.port", show(bus.port))
        addresses: dict[int, str] = {}
        streaming: str | None = None
        for sensor in bus.sensors:
            path = sensor.path
            if sensor.name is not None:
                claim(sensor_names, sensor.name, path, f"{path}.name", show(sensor.name))
            for key in ("unit_id", "raw_unit_id"):
                unit_id = getattr(sensor, key)
                if unit_id is not None:
                    claim(unit_ids, unit_id, f"{path}.{key}", f"{path}.{key}",
                          f"unit id {unit_id}")
            if bus.protocol is not None:
                kind = protocol_name(bus.protocol)
                low, high = ADDRESS_RANGE[bus.protocol]
                if sensor.address is None:
                    pass
                elif not low <= sensor.address <= high:
                    problems.append(f"{path}.address: must be {low}-{high} on a {kind} bus, "
                                    f"not {sensor.address}")
                else:
                    claim(addresses, sensor.address, path, f"{path}.address",
                          f"address {sensor.address}")
                stream = None if sensor.stream_hz is None else \
                    _stream_problem(bus.protocol, sensor.stream_hz)
                if stream:
                    problems.append(f"{path}.stream_hz: {stream}")
                if sensor.raw_unit_id is not None and bus.protocol is not WireProtocol.MODBUS:
                    problems.append(f"{path}.raw_unit_id: only for sensors on a modbus bus; "
                                    f"{bus.path} is {kind}")
            if sensor.stream_hz:
                if streaming is not None:
                    problems.append(f"{path}.stream_hz: only one sensor per bus may stream; "
                                    f"{streaming} already does")
                else:
                    streaming = path
    return problems




def address_warnings(data: Any) -> list[str]:
    """Warnings on the config as written (before defaults are filled in): a Modbus RTU
    sensor with a ``unit_id`` and no ``address``.  Its address then defaults to 1, and
    ``unit_id: 5`` for a sensor at address 5 polls address 1: the two keys look alike
    but name two sides (the gateway's Modbus TCP unit, the sensor's RTU address)."""
    buses = data.get("buses") if isinstance(data, dict) else None
    warnings: list[str] = []
    for i, bus in enumerate(buses if isinstance(buses, list) else []):
        if not isinstance(bus, dict) or \
                protocol_or_none(bus.get("protocol")) is not WireProtocol.MODBUS:
            continue
        sensors = bus.get("sensors")
        for j, sensor in enumerate(sensors if isinstance(sensors, list) else []):
            if isinstance(sensor, dict) and "unit_id" in sensor and sensor.get("address") is None:
                warnings.append(
                    f"buses[{i}].sensors[{j}]: unit_id is the Modbus TCP side; the sensor's "
                    f"RTU address is `address` (not given, so {show(sensor.get('name'))} is "
                    f"polled at address {DEFAULT_ADDRESS[WireProtocol.MODBUS]})")
    return warnings
