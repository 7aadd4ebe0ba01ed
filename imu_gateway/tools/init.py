"""``imu-gateway init``: a commented starter config, from a scan of a port, from
questions, or one of the shipped examples (``imu_gateway/examples``, also in the wheel).

What it writes passes ``check-config``: the text is loaded with the same loader before
it is written, and the poll rate is the highest of :data:`RATES` whose line load
(``capacity.line_loads``, what check-config prints) stays within :data:`TARGET_LOAD`.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from ..capacity import line_loads
from ..config import load_config_text
from ..config.fields import ADDRESS_RANGE, DEFAULT_ADDRESS
from ..errors import GatewayError
from ..model import Series, WireProtocol
from ..protocol.native import BAUD_CODES
from .scan import Found

#: the poll rates offered, fastest first; the first that fits the line is written
RATES = (10.0, 5.0, 2.0, 1.0, 0.5)
#: the share of the line a starter config may ask: room for commands and retries
TARGET_LOAD = 0.75
NAME = re.compile(r"[a-z0-9_-]+")  # the config's rules for a sensor's name
GATEWAY_ID = re.compile(r"[A-Za-z0-9_.-]+")  # and for gateway_id


class InitError(GatewayError, ValueError):
    """A bad answer or option: its text says what was wrong and what is allowed (a leaf
    of ``imu_gateway.errors``'s tree)."""


@dataclass(frozen=True, slots=True)
class StarterSensor:
    name: str
    series: Series
    address: int
    note: str = ""  # a comment on its series line (what the scan could not tell)


@dataclass(frozen=True, slots=True)
class Starter:
    """What a starter config says; :func:`render` writes it with its comments."""

    gateway_id: str
    port: str
    protocol: WireProtocol
    baudrate: int
    sensors: tuple[StarterSensor, ...]
    mqtt_url: str = ""  # empty: no MQTT section
    notes: tuple[str, ...] = ()  # header comments (how it was made, what was left out)


def examples() -> dict[str, str]:
    """The shipped examples: name (file name without .yaml) -> text."""
    folder = resources.files("imu_gateway") / "examples"
    return {item.name.removesuffix(".yaml"): item.read_text(encoding="utf-8")
            for item in folder.iterdir() if item.name.endswith(".yaml")}


def example(name: str) -> str:
    shipped = examples()
    if name not in shipped:
        raise InitError(f"--example {name}: no such example (the examples: "
                        f"{', '.join(sorted(shipped))})")
    return shipped[name]


def _line(indent: int, key: str, value: object, comment: str = "") -> str:
    """``key: value``, its comment in one column."""
    text = f"{' ' * indent}{key}: {value}"
    return f"{text.ljust(34)}# {comment}\n" if comment else f"{text}\n"


def _sensor_lines(sensor: StarterSensor, poll_hz: float) -> str:
    return (_line(6, "- name", sensor.name, "in REST paths and MQTT topics")
            + _line(8, "series", sensor.series.name, sensor.note)
            + _line(8, "address", sensor.address, "on the bus (not the Modbus TCP unit_id)")
            + _line(8, "poll_hz", f"{poll_hz:g}", "readings per second"))


def _mqtt(starter: Starter) -> str:
    if not starter.mqtt_url:
        return ("\n# MQTT: add a section to publish to a broker (docs/mqtt.md):\n"
                "# mqtt:\n#   url: mqtt://localhost:1883\n")
    return (f"\n# MQTT: readings on imu/{starter.gateway_id}/<sensor>/..., Home Assistant "
            f"discovery.\nmqtt:\n  url: {json.dumps(starter.mqtt_url)}\n")


def _text(starter: Starter, poll_hz: float) -> str:
    notes = "".join(f"# {line}\n" for line in starter.notes)
    gateway = _line(0, "gateway_id", starter.gateway_id, "in MQTT topics and /api/v1/health")
    port = _line(4, "port", json.dumps(starter.port), "its /dev/serial/by-id/... name is stable")
    sensors = "".join(_sensor_lines(s, poll_hz) for s in starter.sensors)
    return f"""\
# A starter config written by `imu-gateway init`. Check it after each edit:
#   imu-gateway check-config -c FILE
# Every key: docs/config-reference.md; the file explained: docs/configuration.md.
{notes}
{gateway}
# On a small box (a Pi, one slow core shared with other work): hand the readings to
# MQTT and live streams at most every 20 ms, a fifth less CPU for ~10 ms more latency
# (docs/deployment.md, "Small boxes"). Reads never wait.
# hand_over_ms: 20

buses:
  - name: line-a
{port}\
    baudrate: {starter.baudrate}
    protocol: {starter.protocol.name.lower()}
    sensors:
{sensors}
# Modbus TCP: each sensor's register map (docs/register-map.md) at unit 1, 2, ...
# in the order above. Port 5020 needs no privileges; 502 does (docs/deployment.md).
modbus:
  listen: 0.0.0.0:5020
  allow_writes: false             # true to allow zeroing and calibration over Modbus

# REST API and the live dashboard at http://HOST:8080/. Reachable from other
# machines: set a token (http.token: ${{HTTP_TOKEN}}) before allowing commands.
http:
  listen: 0.0.0.0:8080
{_mqtt(starter)}"""


def render(starter: Starter) -> str:
    """The commented YAML, at the fastest of :data:`RATES` the line carries."""
    for rate in RATES:
        text = _text(starter, rate)
        config = load_config_text(text, "the starter config")  # what check-config loads
        if all(load.load <= TARGET_LOAD for load in line_loads(config.buses)):
            return text
    return text  # the slowest: check-config says what is over, and what to change


def _series(label: str) -> tuple[Series, str]:
    """The scan's series label as a config series, and a note when it was not sure."""
    first = label.split()[0]
    if first not in Series.__members__:
        return Series.VG, "the scan could not tell the series: set IMU, VG, AH or MINS"
    if " or " in label:
        return Series[first], f"the scan said {label.split(' (')[0]}: set the right one"
    if "guessed" in label:
        return Series[first], "guessed from its values: check it"
    return Series[first], ""


def from_scan(port: str, found: Sequence[Found], gateway_id: str) -> Starter:
    """A bus of the sensors found at the first protocol and baud rate found (a bus has
    one of each); the others are named in the header, to be moved to a bus of their
    own."""
    if not found:
        raise InitError(f"--scan {port}: no sensor answered (check the wiring and the "
                        "adapter; `imu-gateway scan --port PORT` shows the search)")
    first = found[0]
    same = [f for f in found if (f.protocol, f.baudrate) == (first.protocol, first.baudrate)]
    notes = [f"Made from a scan of {port}: {len(found)} sensor(s) found."]
    notes += [f"Not in this bus (another protocol or baud rate): {f.line()}"
              for f in found if f not in same]
    sensors = []
    for f in same:
        series, note = _series(f.series)
        sensors.append(StarterSensor(f"{series.name.lower()}{f.address}", series, f.address,
                                     note))
    return Starter(gateway_id, port, first.protocol, first.baudrate, tuple(sensors),
                   notes=tuple(notes))


Ask = Callable[[str, str], str]  # (question, default) -> the answer ("" for the default)


def _choice(ask: Ask, question: str, default: str, parse: Callable[[str], object]) -> str:
    """Asks until the answer parses; a bad one is said, with what is allowed."""
    while True:
        answer = ask(question, default).strip() or default
        try:
            parse(answer)
        except (InitError, KeyError, ValueError) as exc:
            print(f"  {exc}")
            continue
        return answer


def _check(ok: Callable[[str], bool], rule: str) -> Callable[[str], None]:
    def parse(text: str) -> None:
        if not ok(text):
            raise InitError(f"{rule}, not {text!r}")
    return parse


def from_questions(ask: Ask) -> Starter:
    """The starter config from questions, each with a default."""
    gateway_id = _choice(ask, "gateway id", "gateway-1", _check(
        lambda t: GATEWAY_ID.fullmatch(t) is not None, "letters, digits, ., - and _"))
    port = _choice(ask, "serial port", "/dev/ttyUSB0", _check(bool, "a device path"))
    protocol = WireProtocol[_choice(
        ask, "protocol (native or modbus)", "native",
        _check(lambda t: t.upper() in WireProtocol.__members__, "native or modbus")).upper()]
    bauds = sorted(BAUD_CODES.values())
    baud = int(_choice(ask, "baud rate", "9600", _check(
        lambda t: t.isdigit() and int(t) in bauds, f"one of {bauds}")))
    count = int(_choice(ask, "how many sensors on this port", "1",
                        _check(lambda t: t.isdigit() and 1 <= int(t) <= 32, "1-32")))
    sensors: list[StarterSensor] = []
    low, high = DEFAULT_ADDRESS[protocol], ADDRESS_RANGE[protocol][1]
    for i in range(count):
        series = Series[_choice(ask, f"sensor {i + 1}: series (IMU, VG, AH, MINS)", "AH",
                                _check(lambda t: t.upper() in Series.__members__,
                                       "IMU, VG, AH or MINS")).upper()]
        address = int(_choice(ask, f"sensor {i + 1}: bus address", str(low + i),
                              _check(lambda t: t.isdigit() and low <= int(t) <= high,
                                     f"{low}-{high}")))
        name = _choice(ask, f"sensor {i + 1}: name", f"{series.name.lower()}{address}",
                       _check(lambda t: NAME.fullmatch(t) is not None,
                              "lower-case letters, digits, - and _"))
        sensors.append(StarterSensor(name, series, address))
    mqtt = _choice(ask, "MQTT broker URL (empty: none)", "", _check(
        lambda t: t in ("", "none") or t.startswith(("mqtt://", "mqtts://")),
        "mqtt://HOST:PORT, mqtts://HOST:PORT or empty"))
    return Starter(gateway_id, port, protocol, baud, tuple(sensors),
                   "" if mqtt == "none" else mqtt, ("Made from questions.",))


def write(path: str, text: str, force: bool) -> None:
    """Writes ``text`` to a new file; an existing one only with ``force``."""
    target = Path(path)
    if target.exists() and not force:
        raise InitError(f"{path} exists: give --force to overwrite it, or -o another file")
    try:
        with open(target, "w" if force else "x", encoding="utf-8") as file:
            file.write(text)
    except OSError as exc:
        raise InitError(f"cannot write {path}: {exc.strerror or exc}") from None
    os.chmod(target, 0o640)  # the config may come to hold a token
