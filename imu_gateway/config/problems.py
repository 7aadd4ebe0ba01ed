"""What loading reports for a config that failed validation: pydantic's errors in the
config's own words, and what is valid of it, value by value, for the checks across keys
(``checks.py``) to run on as well."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from typing import Annotated, Any, cast, get_args

from pydantic import (
    BaseModel,
    TypeAdapter,
    ValidationError,
)
from pydantic_core import ErrorDetails

from .checks import BusView, SensorView
from .fields import SECRET_KEYS, show, yaml_path
from .schema import BusConfig, GatewayConfig, SensorConfig, fill_defaults

# ------------------------------------------------------------ what is valid of it

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
        adapter = _ADAPTERS[(model, key)] = TypeAdapter(annotated, config=model.model_config)
    try:
        return adapter.validate_python(data[key])
    except ValidationError:
        return None


def salvage(data: Any) -> list[BusView]:
    """What is valid of a config that failed validation, value by value, so that the
    cross-field checks still run on it."""
    data = fill_defaults(data)
    if not isinstance(data, Mapping) or not isinstance(data.get("buses"), list):
        return []
    views = []
    for i, bus in enumerate(data["buses"]):
        if not isinstance(bus, Mapping):
            continue
        raw_sensors = bus.get("sensors")
        sensors = [
            SensorView(
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
        views.append(BusView(
            f"buses[{i}]",
            _field_or_none(BusConfig, "name", bus),
            _field_or_none(BusConfig, "port", bus),
            _field_or_none(BusConfig, "protocol", bus),
            sensors,
        ))
    return views


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
    "tuple_type": "must be a list",
    "model_type": "must be a mapping (key: value)",
    "model_attributes_type": "must be a mapping (key: value)",
    "dict_type": "must be a mapping (key: value)",
}


def pydantic_problem(error: ErrorDetails) -> str:
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
        if not (loc and loc[-1] in SECRET_KEYS):
            message += f", not {show(value)}"
    else:
        message = error["msg"].removeprefix("Value error, ")
        message = message[:1].lower() + message[1:]
    return f"{yaml_path(loc) or '(top level)'}: {message}"
