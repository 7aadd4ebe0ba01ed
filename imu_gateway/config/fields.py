"""The config's limits, the wording of its messages, and the validators of single
fields."""

from __future__ import annotations

import ipaddress
import json
import os
import re
from collections.abc import Mapping
from typing import Annotated, Literal, NamedTuple
from urllib.parse import urlsplit

from pydantic import (
    AfterValidator,
    PlainSerializer,
    PlainValidator,
)
from pydantic_core import PydanticCustomError

from ..model import Series, WireProtocol
from ..protocol.native import BAUD_CODES, OUTPUT_RATE_CODES

BAUD_RATES: tuple[int, ...] = tuple(sorted(BAUD_CODES.values()))
#: Auto-output rates a native sensor has a code for (0 is polled mode).
NATIVE_STREAM_HZ: tuple[int, ...] = tuple(sorted(r for r in OUTPUT_RATE_CODES.values() if r))
#: A Modbus sensor's auto-output interval register (0x1B), in ms.
MODBUS_STREAM_INTERVAL_MS = (10, 65535)
ADDRESS_RANGE: Mapping[WireProtocol, tuple[int, int]] = {
    WireProtocol.NATIVE: (0, 255),
    WireProtocol.MODBUS: (1, 247),
}
DEFAULT_ADDRESS: Mapping[WireProtocol, int] = {WireProtocol.NATIVE: 0, WireProtocol.MODBUS: 1}
UNIT_ID_RANGE = (1, 247)


#: pyserial's URL handlers (serial.serial_for_url).
PYSERIAL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110")
_NAME = re.compile(r"[a-z0-9_-]+")
_GATEWAY_ID = re.compile(r"[A-Za-z0-9_.-]+")
# Values never echoed in a message.
SECRET_KEYS = frozenset({"password", "token"})


# --------------------------------------------------------------------------- messages


def fail(message: str) -> PydanticCustomError:
    """A validator's problem, to raise: pydantic reports it as ``message`` unchanged."""
    # The message travels in the context so that braces in it are never a template.
    return PydanticCustomError("config", "{message}", {"message": message})


def show(value: object) -> str:
    """A short rendering of a bad value for a message: JSON-like, lists and maps by kind."""
    if isinstance(value, str | int | float | bool) or value is None:
        try:
            text = json.dumps(value, ensure_ascii=False)
        except ValueError:  # pragma: no cover - NaN is allowed by json.dumps
            text = repr(value)
    elif isinstance(value, list | tuple):
        text = "a list"
    elif isinstance(value, Mapping):
        text = "a mapping"
    else:
        text = type(value).__name__
    return text if len(text) <= 60 else text[:57] + "..."


def show_number(value: float) -> str:
    """``10.0`` → ``10``, ``0.5`` → ``0.5``."""
    return str(int(value)) if float(value).is_integer() else repr(value)


def yaml_path(loc: tuple[int | str, ...]) -> str:
    """``('buses', 0, 'sensors', 1, 'series')`` → ``buses[0].sensors[1].series``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


# ------------------------------------------------------------------ field validators


def between(low: int, high: int) -> AfterValidator:
    def check(value: int) -> int:
        if not low <= value <= high:
            raise fail(f"must be {low}-{high}, not {value}")
        return value

    return AfterValidator(check)


def _at_least(low: float) -> AfterValidator:
    def check(value: float) -> float:
        if value < low:
            raise fail(f"must be >= {show_number(low)}, not {show_number(value)}")
        return value

    return AfterValidator(check)


def _positive(value: float) -> float:
    if value <= 0:
        raise fail(f"must be > 0, not {show_number(value)}")
    return value


def _name(value: str) -> str:
    if not _NAME.fullmatch(value):
        raise fail(
            f"must match [a-z0-9_-]+ (lower-case letters, digits, _ and -), not {show(value)}"
        )
    return value


def _gateway_id(value: str) -> str:
    if not _GATEWAY_ID.fullmatch(value):
        raise fail(f"must match [A-Za-z0-9_.-]+ (it is part of MQTT topics), not {show(value)}")
    return value


def _sparkplug_id(value: str) -> str:
    if not value or any(c in value for c in "/+#"):
        raise fail(f"must not be empty nor contain /, + or # (Sparkplug ids are topic "
                    f"levels), not {show(value)}")
    return value


def _not_empty(value: str) -> str:
    if not value:
        raise fail("must not be empty")
    return value


def _series(value: object) -> Series:
    if isinstance(value, Series):
        return value
    if isinstance(value, str) and value.strip().upper() in Series.__members__:
        return Series[value.strip().upper()]
    raise fail(f"must be one of {', '.join(s.name for s in Series)}, not {show(value)}")


def _protocol(value: object) -> WireProtocol:
    if isinstance(value, WireProtocol):
        return value
    if isinstance(value, str) and value.strip().upper() in WireProtocol.__members__:
        return WireProtocol[value.strip().upper()]
    raise fail(f"must be one of native, modbus, not {show(value)}")


def protocol_or_none(value: object) -> WireProtocol | None:
    """The protocol ``value`` names, or ``None``: for defaults that depend on it, filled
    in before validation (a bad protocol is reported by its own field)."""
    try:
        return _protocol(value)
    except PydanticCustomError:
        return None


def _baudrate(value: int) -> int:
    if value not in BAUD_RATES:
        raise fail(f"must be one of {', '.join(map(str, BAUD_RATES))}, not {value}")
    return value


def _serial_port(value: str) -> str:
    if not value.strip():
        raise fail("must not be empty")
    if "://" not in value:
        return value  # a device path: /dev/ttyUSB0, /dev/serial/by-id/…, COM3
    scheme = value.split("://", 1)[0].lower()
    if scheme not in PYSERIAL_SCHEMES:
        raise fail(
            f"unknown URL scheme {show(scheme)}: give a device path such as /dev/ttyUSB0 "
            "or a pyserial URL (socket://host:port, rfc2217://host:port, loop://)"
        )
    if scheme in ("socket", "rfc2217"):
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise fail(f"must be {scheme}://host:port, not {show(value)}")
    return value


def _enum_name(value: Series) -> str:
    return value.name


def protocol_name(value: WireProtocol) -> str:
    return value.name.lower()


class ListenAddress(NamedTuple):
    """A ``listen`` value: ``"host:port"``; an IPv6 host in brackets (``"[::]:502"``)."""

    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def _listen(value: object) -> ListenAddress:
    if isinstance(value, ListenAddress):
        return value
    example = 'must be "host:port", e.g. "0.0.0.0:502" or "[::]:502"'
    if not isinstance(value, str):
        raise fail(f"{example}, not {show(value)}")
    host, sep, port = value.strip().rpartition(":")
    if not sep or not host or not port.isdigit():
        raise fail(f"{example}, not {show(value)}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise fail(f"{show(host)} in brackets is not an IPv6 address") from None
    elif ":" in host:
        raise fail(f'an IPv6 host goes in brackets, e.g. "[::]:502", not {show(value)}')
    if int(port) > 65535:
        raise fail(f"port must be 0-65535, not {port}")
    return ListenAddress(host, int(port))


IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def _network(value: object) -> IPNetwork:
    if isinstance(value, ipaddress.IPv4Network | ipaddress.IPv6Network):
        return value
    if isinstance(value, str):
        try:
            return ipaddress.ip_network(value.strip(), strict=False)
        except ValueError:
            pass
    raise fail(f"must be an IPv4 or IPv6 network such as 10.0.0.0/8, not {show(value)}")


def _network_text(value: IPNetwork) -> str:
    return str(value)


def _mqtt_url(value: str) -> str:
    parts = urlsplit(value)
    if parts.scheme not in ("mqtt", "mqtts"):
        raise fail(f"must be mqtt://host[:port] or mqtts://host[:port], not {show(value)}")
    if "@" in parts.netloc:
        raise fail("must not hold credentials: use the username and password keys")
    try:
        port = parts.port
    except ValueError:
        raise fail(f"port must be 0-65535, not {show(value)}") from None
    if not parts.hostname:
        raise fail(f"has no host: {show(value)}")
    if parts.path not in ("", "/") or parts.query or parts.fragment or port == 0:
        raise fail(f"must be {parts.scheme}://host[:port] and nothing more, not {show(value)}")
    return value


def _mqtt_urls(value: str | list[str]) -> str | list[str]:
    """One broker, or the nodes of a cluster: each as ``_mqtt_url``, one scheme for all
    (the TLS settings are shared), none twice."""
    if isinstance(value, str):
        return _mqtt_url(value)
    if not value:
        raise fail("must name at least one broker")
    for url in value:
        _mqtt_url(url)
    if len({urlsplit(url).scheme for url in value}) > 1:
        raise fail("must use one scheme for every broker, all mqtt:// or all mqtts:// "
                    "(they share the TLS settings)")
    if len(set(value)) < len(value):
        raise fail("names a broker twice")
    return value


def _mqtt_protocol(value: object) -> str:
    if isinstance(value, int | float) and not isinstance(value, bool) and value == 5:
        return "5"
    if isinstance(value, str) and value.strip() in ("3.1.1", "5", "5.0"):
        return "3.1.1" if value.strip() == "3.1.1" else "5"
    raise fail(f'must be "3.1.1" or 5, not {show(value)}')


def _base_topic(value: str) -> str:
    if not value:
        raise fail("must not be empty")
    if any(c in value for c in "+#\0"):
        raise fail(f"must not contain the MQTT wildcards + or #, not {show(value)}")
    if value.startswith("/") or value.endswith("/"):
        raise fail(f"must not start or end with /, not {show(value)}")
    return value


def _existing_file(value: str) -> str:
    if not os.path.isfile(value):
        raise fail(f"no such file: {value}")
    return value


def _in_existing_folder(value: str) -> str:
    folder = os.path.dirname(value) or "."
    if not value or not os.path.isdir(folder):
        raise fail(f"no such folder: {folder} (for {value}); create it first")
    return value


Name = Annotated[str, AfterValidator(_name)]
NonEmpty = Annotated[str, AfterValidator(_not_empty)]
UnitId = Annotated[int, between(*UNIT_ID_RANGE)]
PositiveInt = Annotated[int, AfterValidator(_positive)]
NonNegativeInt = Annotated[int, _at_least(0)]
NonNegative = Annotated[float, _at_least(0)]
SeriesField = Annotated[
    Series, PlainValidator(_series), PlainSerializer(_enum_name, when_used="json")
]
ProtocolField = Annotated[
    WireProtocol, PlainValidator(_protocol), PlainSerializer(protocol_name, when_used="json")
]
Listen = Annotated[ListenAddress, PlainValidator(_listen), PlainSerializer(str, when_used="json")]
Network = Annotated[
    IPNetwork, PlainValidator(_network), PlainSerializer(_network_text, when_used="json")
]
ExistingFile = Annotated[str, AfterValidator(_existing_file)]
FileToKeep = Annotated[str, AfterValidator(_in_existing_folder)]
SerialPort = Annotated[str, AfterValidator(_serial_port)]
BaudRate = Annotated[int, AfterValidator(_baudrate)]
GatewayId = Annotated[str, AfterValidator(_gateway_id)]
SparkplugId = Annotated[str, AfterValidator(_sparkplug_id)]
MqttUrls = Annotated[str | list[str], AfterValidator(_mqtt_urls)]
MqttProtocol = Annotated[Literal["3.1.1", "5"], PlainValidator(_mqtt_protocol)]
#: an MQTT topic prefix (``base_topic``, ``discovery_prefix``)
TopicPrefix = Annotated[str, AfterValidator(_base_topic)]
