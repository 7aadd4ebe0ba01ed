"""Modbus Read Device Identification (function 0x2B, MEI type 0x0E), sans-IO.

A SCADA system asks a Modbus server what it is before it reads registers: who made it,
which product, which revision.  Each sensor's unit id answers for that sensor; unit
255 answers for the gateway itself.  One row per object below (``OBJECTS``); the
server's answers and the table in ``docs/register-map.md`` both come from it.

The rules (Modbus Application Protocol V1.1b3, section 6.21):

* Read codes 1 (basic: objects 0-2), 2 (regular: 0-6) and 3 (extended: there are no
  extended objects, so the regular ones) are *stream* access: the objects of the
  category from the object id asked for.  An object id that is not in the category
  restarts the stream at its first object.  What does not fit in one answer is
  announced with "more follows" and the id to ask for next.
* Read code 4 is *individual* access: that one object, or exception 02 when it does
  not exist.
* Any other read code is exception 03; a request of the wrong length too.  Another
  MEI type (13, CANopen) is exception 01.
* The conformity level is 0x82: regular objects, stream and individual access.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ... import __version__
from ...modbus_codes import ILLEGAL_ADDRESS, ILLEGAL_FUNCTION, ILLEGAL_VALUE
from ...model import Series, WireProtocol

FUNCTION, MEI_TYPE = 0x2B, 0x0E
CONFORMITY = 0x82  # regular identification, stream and individual access
STREAM_CODES = {1: range(0x00, 0x03), 2: range(0x00, 0x07), 3: range(0x00, 0x07)}
INDIVIDUAL = 4
MAX_PDU = 253  # a Modbus PDU's size limit
#: an answer's header: function, MEI type, code, conformity, more follows, next id, count
HEADER = 7
#: the longest object value: one object alone (its id and length bytes) fits an answer
MAX_VALUE = MAX_PDU - HEADER - 2

#: The sensors' maker, as the vendor's Modbus document names it (docs/protocol-notes.md).
VENDOR_NAME = "Wuxi Bewis Sensing Technology"
VENDOR_URL = "www.bwsensing.com"

SERIES_TITLES = {
    Series.IMU: "IMU inertial measurement unit",
    Series.VG: "VG vertical gyro",
    Series.AH: "AH attitude and heading reference",
    Series.MINS: "MINS miniature inertial navigation system",
}


@dataclass(frozen=True, slots=True)
class Identity:
    """What one unit id says it is."""

    series: Series | None  # None: the gateway itself (unit 255)
    protocol: WireProtocol | None
    name: str  # the sensor's name in the config, or the gateway_id


@dataclass(frozen=True, slots=True)
class IdObject:
    """One identification object: its id, its name in the standard, and its value
    for a sensor and for the gateway (None: the gateway has none)."""

    id: int
    name: str
    sensor: Callable[[Identity], str]
    gateway: Callable[[Identity], str] | None

    def value(self, who: Identity) -> bytes:
        text = self.sensor(who) if who.series is not None else \
            self.gateway(who) if self.gateway is not None else ""
        return text.encode("ascii", "replace")[:MAX_VALUE]

    def has(self, who: Identity) -> bool:
        return who.series is not None or self.gateway is not None


def _series(who: Identity) -> str:
    assert who.series is not None
    return who.series.name


def _model(who: Identity) -> str:
    assert who.series is not None and who.protocol is not None
    wire = "native protocol" if who.protocol is WireProtocol.NATIVE else "Modbus RTU"
    return f"{who.series.name} over {wire}"


def _title(who: Identity) -> str:
    assert who.series is not None
    return SERIES_TITLES[who.series]


OBJECTS: tuple[IdObject, ...] = (
    IdObject(0x00, "VendorName", lambda w: VENDOR_NAME, lambda w: "imu-gateway project"),
    IdObject(0x01, "ProductCode", _series, lambda w: "imu-gateway"),
    IdObject(0x02, "MajorMinorRevision",
             lambda w: f"imu-gateway {__version__}", lambda w: __version__),
    IdObject(0x03, "VendorUrl", lambda w: VENDOR_URL, None),  # the project has none
    IdObject(0x04, "ProductName", _title, lambda w: "imu-gateway"),
    IdObject(0x05, "ModelName", _model, lambda w: "Modbus TCP gateway"),
    IdObject(0x06, "UserApplicationName", lambda w: w.name, lambda w: w.name),
)
BY_ID = {o.id: o for o in OBJECTS}


def answer(pdu: bytes, who: Identity) -> bytes:
    """The answer PDU to a Read Device Identification request PDU (``0x2B 0x0E code
    object``), or the exception answer that refuses it."""
    if len(pdu) >= 2 and pdu[1] != MEI_TYPE:  # CANopen (13) or another: not served
        return bytes((FUNCTION | 0x80, ILLEGAL_FUNCTION))
    if len(pdu) != 4:
        return bytes((FUNCTION | 0x80, ILLEGAL_VALUE))
    code, first = pdu[2], pdu[3]
    if code == INDIVIDUAL:
        if first not in BY_ID or not BY_ID[first].has(who):
            return bytes((FUNCTION | 0x80, ILLEGAL_ADDRESS))
        return _pack(code, [BY_ID[first]], who, more=None)
    if code not in STREAM_CODES:
        return bytes((FUNCTION | 0x80, ILLEGAL_VALUE))
    ids = STREAM_CODES[code]
    if first not in ids:
        first = ids[0]  # the standard's rule: restart at the category's start
    objects = [BY_ID[i] for i in ids if i >= first and BY_ID[i].has(who)]
    room, taken = MAX_PDU - HEADER, []
    for obj in objects:
        size = 2 + len(obj.value(who))
        if size > room:
            break
        room -= size
        taken.append(obj)
    more = objects[len(taken)].id if len(taken) < len(objects) else None
    return _pack(code, taken, who, more)


def _pack(code: int, objects: list[IdObject], who: Identity, more: int | None) -> bytes:
    out = bytearray((FUNCTION, MEI_TYPE, code, CONFORMITY,
                     0xFF if more is not None else 0x00, more or 0, len(objects)))
    for obj in objects:
        value = obj.value(who)
        out += bytes((obj.id, len(value))) + value
    return bytes(out)


def markdown() -> list[str]:
    """The section of ``docs/register-map.md`` about device identification."""
    sensor = Identity(Series.AH, WireProtocol.MODBUS, "boom")
    gateway = Identity(None, None, "line-3-box")
    return [
        "## Device identification (FC 43 / MEI 14)",
        "",
        "Read Device Identification answers on every sensor's unit id for that sensor, "
        "and on unit 255 for the gateway. Read codes 1 (basic), 2 (regular) and 3 "
        "(extended: there are no extended objects, so the regular ones) stream the "
        "category's objects from the object id asked for (one that is not in the "
        "category restarts at its first object); read code 4 reads one object "
        "(exception 02 if it does not exist). Other read codes: exception 03; other MEI "
        "types (13, CANopen): exception 01. "
        f"Conformity level 0x{CONFORMITY:02X} (regular, stream and individual access). "
        "Values are ASCII. The sensors report no firmware version, so a sensor's "
        "revision is the gateway's (docs/protocol-notes.md). Examples below: an AH "
        "named `boom` on a Modbus RTU line, and a gateway whose `gateway_id` is "
        "`line-3-box`.",
        "",
        "| id | object | a sensor's (example) | the gateway's, unit 255 (example) |",
        "|---|---|---|---|",
        *(f"| 0x{o.id:02X} | {o.name} | {o.value(sensor).decode()} | "
          f"{o.value(gateway).decode() if o.has(gateway) else '(none)'} |"
          for o in OBJECTS),
        "",
    ]
