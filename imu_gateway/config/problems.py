"""Problems that span several fields (a name used twice, a stream the baud rate
cannot carry), and pydantic's errors in the config's own words."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, cast, get_args

from pydantic import (
    BaseModel,
    TypeAdapter,
    ValidationError,
)
from pydantic_core import ErrorDetails

from ..model import WireProtocol
from .fields import (
    _SECRET_KEYS,
    ADDRESS_RANGE,
    MODBUS_STREAM_INTERVAL_MS,
    NATIVE_STREAM_HZ,
    _number,
    _path,
    _protocol_name,
    _show,
)
from .schema import BusConfig, GatewayConfig, SensorConfig, _fill_defaults, _Model

# --------------------------------------------------------------- cross-field checks


@dataclass(frozen=True, slots=True)
class _SensorView:
    """A sensor for the cross-field checks: each value ``None`` when absent or invalid."""

    path: str
    name: str | None
    address: int | None
    unit_id: int | None
    raw_unit_id: int | None
    stream_hz: float | None


@dataclass(frozen=True, slots=True)
class _BusView:
    path: str
    name: str | None
    port: str | None
    protocol: WireProtocol | None
    sensors: list[_SensorView]


def _views(config: GatewayConfig) -> list[_BusView]:
    return [
        _BusView(f"buses[{i}]", bus.name, bus.port, bus.protocol, [
            _SensorView(f"buses[{i}].sensors[{j}]", s.name, s.address, s.unit_id,
                        s.raw_unit_id, s.stream_hz)
            for j, s in enumerate(bus.sensors)
        ])
        for i, bus in enumerate(config.buses)
    ]


_ADAPTERS: dict[tuple[type[BaseModel], str], TypeAdapter[Any]] = {}


def _field_or_none(model: type[BaseModel], key: str, data: Mapping[str, Any]) -> Any:
    """One field of ``model`` validated on its own: its default when absent, ``None``
    when invalid (the field's own problem is reported by pydantic)."""
    field = model.model_fields[key]
    if key not in data:
        return field.get_default(call_default_factory=True)
    adapter = _ADAPTERS.get((model, key))
    if adapter is None:
        annotated: Any = field.annotation
        if field.metadata:
            annotated = cast(Any, Annotated)[(annotated, *field.metadata)]
        adapter = _ADAPTERS[(model, key)] = TypeAdapter(annotated, config=_Model.model_config)
    try:
        return adapter.validate_python(data[key])
    except ValidationError:
        return None


def _salvage(data: Any) -> list[_BusView]:
    """What is valid of a config that failed validation, value by value, so that the
    cross-field checks still run on it."""
    data = _fill_defaults(data)
    if not isinstance(data, Mapping) or not isinstance(data.get("buses"), list):
        return []
    views = []
    for i, bus in enumerate(data["buses"]):
        if not isinstance(bus, Mapping):
            continue
        raw_sensors = bus.get("sensors")
        sensors = [
            _SensorView(
                f"buses[{i}].sensors[{j}]",
                _field_or_none(SensorConfig, "name", raw),
                _field_or_none(SensorConfig, "address", raw),
                _field_or_none(SensorConfig, "unit_id", raw),
                _field_or_none(SensorConfig, "raw_unit_id", raw),
                _field_or_none(SensorConfig, "stream_hz", raw),
            )
            for j, raw in enumerate(raw_sensors if isinstance(raw_sensors, list) else [])
            if isinstance(raw, Mapping)
        ]
        views.append(_BusView(
            f"buses[{i}]",
            _field_or_none(BusConfig, "name", bus),
            _field_or_none(BusConfig, "port", bus),
            _field_or_none(BusConfig, "protocol", bus),
            sensors,
        ))
    return views


def _stream_problem(protocol: WireProtocol, hz: float) -> str | None:
    if hz == 0:
        return None
    if protocol is WireProtocol.NATIVE:
        if hz not in NATIVE_STREAM_HZ:
            rates = ", ".join(map(str, NATIVE_STREAM_HZ))
            return f"must be 0 or one of {rates} on a native bus, not {_number(hz)}"
        return None
    low, high = MODBUS_STREAM_INTERVAL_MS
    if not low <= round(1000 / hz) <= high:
        return (
            f"on a modbus bus the output interval round(1000/stream_hz) must be "
            f"{low}-{high} ms (stream_hz about 0.016-100), not {_number(hz)}"
        )
    return None


def _cross_problems(buses: list[_BusView]) -> list[str]:
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
            claim(bus_names, bus.name, bus.path, f"{bus.path}.name", _show(bus.name))
        if bus.port is not None:
            claim(ports, bus.port, bus.path, f"{bus.path}.port", _show(bus.port))
        addresses: dict[int, str] = {}
        streaming: str | None = None
        for sensor in bus.sensors:
            path = sensor.path
            if sensor.name is not None:
                claim(sensor_names, sensor.name, path, f"{path}.name", _show(sensor.name))
            for key in ("unit_id", "raw_unit_id"):
                unit_id = getattr(sensor, key)
                if unit_id is not None:
                    claim(unit_ids, unit_id, f"{path}.{key}", f"{path}.{key}",
                          f"unit id {unit_id}")
            if bus.protocol is not None:
                kind = _protocol_name(bus.protocol)
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


# --------------------------------------------------- pydantic errors, in one place


def _model_in(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _unknown_key(loc: tuple[int | str, ...]) -> str:
    model: type[BaseModel] = GatewayConfig
    for part in loc[:-1]:
        if isinstance(part, str):
            field = model.model_fields.get(part)
            inner = _model_in(field.annotation) if field else None
            if inner is None:
                break
            model = inner
    allowed = list(model.model_fields)
    close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown key (allowed: {', '.join(allowed)}){hint}"


_TYPE_MESSAGES: Mapping[str, str] = {
    "int_type": "must be a whole number",
    "int_parsing": "must be a whole number",
    "int_from_float": "must be a whole number",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "list_type": "must be a list",
    "model_type": "must be a mapping (key: value)",
    "model_attributes_type": "must be a mapping (key: value)",
    "dict_type": "must be a mapping (key: value)",
}


def _pydantic_problem(error: ErrorDetails) -> str:
    """One pydantic error as ``<yaml path>: <message>``."""
    loc = error["loc"]
    kind = error["type"]
    value = error.get("input")
    if kind == "config":
        message = error["msg"]
    elif kind == "missing":
        message = "required"
    elif kind == "extra_forbidden":
        message = _unknown_key(loc)
    elif kind == "too_short":
        message = "must not be empty"
    elif kind in _TYPE_MESSAGES:
        message = _TYPE_MESSAGES[kind]
        if kind == "string_type" and isinstance(value, bool):
            message += " (put it in quotes)"
        if not (loc and loc[-1] in _SECRET_KEYS):
            message += f", not {_show(value)}"
    else:
        message = error["msg"].removeprefix("Value error, ")
        message = message[:1].lower() + message[1:]
    return f"{_path(loc) or '(top level)'}: {message}"
