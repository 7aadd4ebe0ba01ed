"""Every example frame printed in the two protocol documents, as one declarative table.

Native: Analog Technologies, "IMU/VG/AH/MINS Digital Protocol", V3.0, sections
2.1-2.26.
Modbus RTU: "IMU VG AH MINS Series Modbus Protocol", sections 2.1-2.13.

Each row holds the hex string exactly as printed and what it must decode to:

* native rows: ``name`` is the command of ``native.COMMANDS`` and ``values`` are all of
  the frame's fields, written as the document prints them (-34.63, 0.0107 ...);
* Modbus rows: ``name`` is ``read_request``, ``read_response`` or, for FC06, the name of
  the written register in ``modbus_rtu.REGISTERS``.  A read request's values are its
  ``start`` and ``count``; a read answer's are the register values read in the light of
  its request's ``start``; a write's is the decoded ``value``.  The Modbus document
  prints one value per float answer: ``printed`` names those keys, the others were taken
  from decoding (they guard against regressions, not against the document).

Deviation from the document, on purpose: Modbus 2.4 prints the save frame as
``01 06 00 0F 00 00 00 B9 C9``, with a stray ``00`` (nine bytes, which is no FC06
frame).  The table holds the corrected ``01 06 00 0F 00 00 B9 C9``;
``test_modbus_rtu.test_save_example_typo`` checks both.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from imu_gateway.model import Series

NATIVE = "native"
MODBUS = "modbus"
REQUEST = "request"
ANSWER = "answer"


@dataclass(frozen=True)
class Vector:
    section: str
    protocol: str
    direction: str
    hex: str
    name: str
    values: Mapping[str, Any] = field(default_factory=dict)
    #: native: a series that sends (answers) or accepts (requests) this frame
    series: Series | None = None
    #: native: the address byte; Modbus: the unit id
    address: int = 0
    #: Modbus read answers: the first register of the request they answer
    start: int | None = None
    #: keys of ``values`` the document itself prints (``None``: all of them)
    printed: tuple[str, ...] | None = None
    note: str = ""

    @property
    def raw(self) -> bytes:
        return bytes.fromhex(self.hex)

    @property
    def id(self) -> str:
        return f"{self.protocol}-{self.section}-{self.direction}"

    @property
    def printed_values(self) -> dict[str, Any]:
        keys = self.values.keys() if self.printed is None else self.printed
        return {k: self.values[k] for k in keys}


def _n(section: str, direction: str, hex_: str, name: str, series: Series | None = None,
       note: str = "", **values: Any) -> Vector:
    return Vector(section, NATIVE, direction, hex_, name, values, series, note=note)


def _m(section: str, direction: str, hex_: str, name: str, values: Mapping[str, Any],
       *, unit: int = 1, start: int | None = None, printed: tuple[str, ...] | None = None,
       note: str = "") -> Vector:
    return Vector(section, MODBUS, direction, hex_, name, values, None, unit, start, printed,
                  note)


Q, A = REQUEST, ANSWER
IMU, VG, AH, MINS = Series.IMU, Series.VG, Series.AH, Series.MINS

NATIVE_VECTORS: tuple[Vector, ...] = (
    _n("2.1", Q, "77 04 00 01 05", "read_pitch", VG),
    _n("2.1", A, "77 07 00 81 10 34 63 2F", "read_pitch", VG, pitch=-34.63),
    _n("2.2", Q, "77 04 00 02 06", "read_roll", VG),
    _n("2.2", A, "77 07 00 82 01 23 57 04", "read_roll", VG, roll=123.57),
    _n("2.3", Q, "77 04 00 04 08", "read_angles", VG),
    _n("2.3", A, "77 0D 00 84 00 02 01 10 00 51 00 00 00 F5", "read_angles", VG,
       pitch=2.01, roll=-0.51, yaw=0.0),
    _n("2.4", Q, "77 05 00 0B 02 12", "set_baudrate", baudrate=9600),
    _n("2.5", Q, "77 05 00 0F 01 15", "set_address", new_address=1),
    _n("2.5", Q, "77 05 00 0F 0A 1E", "set_address", new_address=0x0A,
       note="the note's variant: address 00 -> 0A"),
    _n("2.6", Q, "77 04 00 1F 23", "read_address"),
    _n("2.7", Q, "77 04 00 0A 0E", "save"),
    _n("2.8", Q, "77 05 00 05 01 0B", "set_zero_type", zero_type="relative"),
    _n("2.9", Q, "77 04 00 0D 11", "read_zero_type"),
    _n("2.10", Q, "77 04 00 54 58", "read_accel"),
    _n("2.10", A, "77 0D 00 54 00 01 07 00 94 21 10 06 30 64", "read_accel", VG,
       accel_x=0.0107, accel_y=0.9421, accel_z=-0.0630),
    _n("2.11", Q, "77 04 00 50 54", "read_gyro"),
    _n("2.11", A, "77 0D 00 50 10 93 76 14 98 87 00 14 03 C0", "read_gyro", VG,
       gyro_x=-93.76, gyro_y=-498.87, gyro_z=14.03),
    _n("2.12", Q, "77 04 00 57 5B", "read_quaternion", VG),
    _n("2.12", A, "77 14 00 57 00 99 99 96 00 00 02 90 10 00 26 73 10 00 00 01 7F",
       "read_quaternion", VG, q0=0.999996, q1=0.000290, q2=-0.002673, q3=-0.000001),
    _n("2.13", Q, "77 04 00 59 5D", "read_all", IMU),
    _n("2.13", A, "77 16 00 84 10 93 76 12 98 87 00 14 03 00 01 07 00 94 21 10 06 30 FE",
       "read_all", IMU, note="IMU answers 0x59 with 0x84 and 18 bytes",
       gyro_x=-93.76, gyro_y=-298.87, gyro_z=14.03,
       accel_x=0.0107, accel_y=0.9421, accel_z=-0.0630),
    _n("2.14", Q, "77 04 00 59 5D", "read_all", VG),
    _n("2.14", A,
       "77 2F 00 59 10 00 60 10 03 06 00 00 00 10 01 07 10 05 43 01 01 54 "
       "10 00 13 10 00 04 00 00 09 10 87 06 35 00 01 76 91 00 02 06 94 00 49 11 75 5C",
       "read_all", VG,
       pitch=-0.6, roll=-3.06, yaw=0.0,
       accel_x=-0.0107, accel_y=-0.0543, accel_z=1.0154,
       gyro_x=-0.13, gyro_y=-0.04, gyro_z=0.09,
       q0=-0.870635, q1=0.017691, q2=0.020694, q3=0.491175),
    _n("2.15", Q, "77 04 00 59 5D", "read_all", AH),
    _n("2.15", A,
       "77 38 00 59 10 13 15 00 25 58 02 51 87 10 18 07 10 28 16 01 02 65 "
       "10 06 48 01 24 13 00 03 88 01 59 62 01 63 91 14 14 58 "
       "10 22 83 75 10 18 33 49 10 16 55 78 00 93 99 14 58",
       "read_all", AH,
       note="the document's text cuts the yaw to '+251.'; the bytes 02 51 87 and "
            "the example reading JSON of docs/mqtt.md say 251.87",
       pitch=-13.15, roll=25.58, yaw=251.87,
       accel_x=-0.1807, accel_y=-0.2816, accel_z=1.0265,
       gyro_x=-6.48, gyro_y=124.13, gyro_z=3.88,
       mag_x=0.15962, mag_y=0.16391, mag_z=-0.41458,
       q0=-0.228375, q1=-0.183349, q2=-0.165578, q3=0.939914),
    _n("2.16", Q, "77 05 00 56 00 5B", "set_output_type", output_type=0),
    _n("2.16", A, "77 05 00 56 00 5B", "set_output_type", VG,
       note="a status, printed as 00 whatever type was asked (as 2.17's); the same bytes "
            "as the request for type 00",
       result="success"),
    _n("2.17", Q, "77 05 00 0C 00 11", "set_output_rate", rate_hz=0),
    _n("2.18", Q, "77 04 00 52 56", "calibrate_gyro"),
    _n("2.19", Q, "77 04 00 82 86", "clear_heading", MINS),
    _n("2.20", Q, "77 07 00 84 01 00 00 8C", "set_relative_heading", MINS, degrees=100.0),
    _n("2.21", Q, "77 06 00 06 02 08 16", "set_declination", AH, degrees=20.8),
    _n("2.22", Q, "77 04 00 07 0B", "read_declination", AH),
    _n("2.23", Q, "77 04 00 55 59", "read_mag", AH),
    _n("2.23", A, "77 0D 00 55 11 55 25 00 34 52 13 46 16 E2", "read_mag", AH,
       mag_x=-0.15525, mag_y=0.03452, mag_z=-0.34616),
    _n("2.24", Q, "77 04 00 10 14", "clear_mag_calibration", AH),
    _n("2.25", Q, "77 04 00 11 15", "start_mag_calibration", AH),
    _n("2.26", Q, "77 04 00 12 16", "finish_mag_calibration", AH),
)

#: The save frame as Modbus 2.4 prints it (request and answer), stray ``00`` and all.
MODBUS_SAVE_AS_PRINTED = "01 06 00 0F 00 00 00 B9 C9"

RR, RA = "read_request", "read_response"

MODBUS_VECTORS: tuple[Vector, ...] = (
    _m("2.1", Q, "01 03 00 01 00 01 D5 CA", RR, {"start": 1, "count": 1}),
    _m("2.1", A, "01 03 02 4E 7D 4D C5", RA, {"pitch": 0.93}, start=1),
    _m("2.2", Q, "01 03 00 01 00 02 95 CB", RR, {"start": 1, "count": 2}),
    _m("2.2", A, "01 03 04 50 A7 4C EE EE 5C", RA, {"pitch": 6.47, "roll": -3.06}, start=1,
       printed=(), note="the document prints no values for this answer"),
    _m("2.3", Q, "01 06 00 0B 00 02 79 C9", "set_baudrate", {"value": 9600},
       note="no answer: takes effect at once"),
    _m("2.4", Q, "01 06 00 0F 00 00 B9 C9", "save", {"value": 0},
       note="printed with a stray 00: " + MODBUS_SAVE_AS_PRINTED),
    _m("2.4", A, "01 06 00 0F 00 00 B9 C9", "save", {"value": 0},
       note="printed with a stray 00: " + MODBUS_SAVE_AS_PRINTED),
    _m("2.5", Q, "01 06 00 0A 00 00 A9 C8", "set_zero_type", {"value": "absolute"}),
    _m("2.5", A, "01 06 00 0A 00 00 A9 C8", "set_zero_type", {"value": "absolute"}),
    _m("2.6", Q, "01 03 00 05 00 01 94 0B", RR, {"start": 5, "count": 1}),
    _m("2.6", A, "01 03 02 00 01 79 84", RA, {"zero_type": "relative"}, start=5),
    _m("2.7", Q, "01 06 00 0D 00 03 58 08", "set_address", {"value": 3}),
    _m("2.7", A, "03 06 00 0D 00 03 59 EA", "set_address", {"value": 3}, unit=3,
       note="answered from the new address"),
    _m("2.8", Q, "01 03 00 28 00 06 45 C0", RR, {"start": 0x28, "count": 6}),
    _m("2.8", A, "01 03 0C DE E4 37 3C E1 7D D5 3C D9 93 7C 3F C0 2C", RA,
       {"accel_x": 0.011224, "accel_y": 0.026061, "accel_z": 0.986631},
       start=0x28, printed=("accel_x",)),
    _m("2.9", Q, "01 03 00 2E 00 06 A5 C1", RR, {"start": 0x2E, "count": 6}),
    _m("2.9", A, "01 03 0C D7 88 80 3D CF 2F 0A BD F1 82 08 BC 46 18", RA,
       {"gyro_x": 0.062761, "gyro_y": -0.033737, "gyro_z": -0.008332},
       start=0x2E, printed=("gyro_x",)),
    _m("2.10", Q, "01 03 00 3A 00 08 64 01", RR, {"start": 0x3A, "count": 8}),
    _m("2.10", A, "01 03 10 21 E7 55 3F A5 A0 1B 3D 7A 1A 30 BD BD E0 0B BF 5C B4", RA,
       {"q0": 0.835558, "q1": 0.037995, "q2": -0.042994, "q3": -0.546398},
       start=0x3A, printed=("q0",)),
    _m("2.11", Q, "01 06 00 10 00 00 88 0F", "calibrate_gyro", {"value": 0}),
    _m("2.11", A, "01 06 00 10 00 00 88 0F", "calibrate_gyro", {"value": 0},
       note="0 = started; a later echo of 1 = done"),
    _m("2.12", Q, "01 06 00 1B 00 14 F9 C2", "output_interval_ms", {"value": 20}),
    _m("2.12", A, "01 06 00 1B 00 14 F9 C2", "output_interval_ms", {"value": 20}),
    _m("2.13", Q, "01 06 00 1C 01 04 48 5F", "output_registers", {"value": (1, 4)}),
    _m("2.13", A, "01 06 00 1C 01 04 48 5F", "output_registers", {"value": (1, 4)}),
)

#: The float answers' values in the document's own long spelling: each is the same
#: float32 as the shortest form in the table (0.01122399978 is 0.011224 as float32).
MODBUS_FLOAT_TEXT: Mapping[str, tuple[str, float]] = {
    "2.8": ("accel_x", 0.01122399978),
    "2.9": ("gyro_x", 0.062761),
    "2.10": ("q0", 0.835557997),
}

ALL_VECTORS: tuple[Vector, ...] = NATIVE_VECTORS + MODBUS_VECTORS


def ids(vectors: tuple[Vector, ...]) -> list[str]:
    """Unique pytest ids (2.5 has two requests, 2.13-2.15 share one)."""
    seen: dict[str, int] = {}
    out = []
    for v in vectors:
        n = seen[v.id] = seen.get(v.id, 0) + 1
        out.append(v.id if n == 1 else f"{v.id}-{n}")
    return out
