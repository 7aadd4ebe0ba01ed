"""The Modbus TCP register map, as one declarative table.

The server answers from it, ``docs/register-map.md`` is generated from it
(``python -m imu_gateway.frontends.modbus.map > docs/register-map.md``; a test fails when
the file is out of date), and nothing else describes it.

Each sensor's map is kept as a byte image: the measured values are packed at the
first read after a reading arrived (a 100 Hz sensor that no client reads costs no
packing), the status and command blocks when they are read (they change with time and
settings).  A read is then a bounds check and a slice.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from ...cache import Snapshot
from ...commands import CATALOGUE, CommandSpec
from ...model import (
    CAPABILITIES,
    VALUE_GROUPS,
    Group,
    KnownSettings,
    Reading,
    Series,
    WireProtocol,
    shortest_float32,
)
from ...normalise import field_values
from ...stats import BusStats
from . import alarms, ident

INT32_MIN = -(2**31)
NAN32 = struct.pack(">f", math.nan)


class Type(enum.Enum):
    U16 = (1, "u16")
    U32 = (2, "u32")
    I32 = (2, "i32")
    F32 = (2, "f32")
    MASK = (alarms.MASK_WORDS, f"{alarms.MASK_WORDS} × u16")  # bits, 16 a word

    @property
    def words(self) -> int:
        return self.value[0]


@dataclass(frozen=True, slots=True)
class Register:
    address: int
    type: Type
    name: str
    description: str
    group: Group | None = None  # measured values: the group that carries it
    scale: int = 1  # i32 copies: value × scale
    command: str | None = None  # holding registers a write turns into this command
    series: frozenset[Series] = frozenset(Series)  # who has it (commands)


STATUS_BITS = {"online": 0, "stale": 1, "busy": 2, "streaming": 3, "no_reading": 4}

def _command_type(spec: CommandSpec) -> Type:
    """A float32 for an angle, else one word (a flag, or a choice's code)."""
    name = spec.argument
    return Type.F32 if name and spec.args.model_fields[name].annotation is float else Type.U16


#: The values in the map's order (the reading JSON's): the sixteen measured, then the
#: derived (appended, so no measured value's address moved when they came): name,
#: group, the i32 copy's scale (it holds round(value × scale): the group's resolution),
#: unit.
_MEASURED: tuple[tuple[str, Group, int, str], ...] = tuple(
    (name, group, spec.scale, spec.symbol)
    for group, spec in VALUE_GROUPS.items() for name in spec.fields
)
FLOAT_BASE, INT_BASE, ALARM_BASE, COMMAND_BASE = 100, 200, 300, 1000
MINS, AH = frozenset({Series.MINS}), frozenset({Series.AH})

REGISTERS: tuple[Register, ...] = (
    Register(0, Type.U16, "status", "bits: 0 online, 1 stale, 2 busy (save or calibration), "
             "3 streaming, 4 no reading yet"),
    Register(1, Type.U16, "age_ms", "age of the latest sample in ms, saturating at 65535"),
    Register(2, Type.U32, "seq", "sample sequence number (increments on each new reading)"),
    Register(4, Type.U32, "errors", "error count (timeouts, bad checksums, bad frames)"),
    Register(6, Type.U16, "series", "series: 1 IMU, 2 VG, 3 AH, 4 MINS"),
    Register(7, Type.U16, "protocol", "protocol: 0 native, 1 modbus"),
    Register(8, Type.U16, "bus_address", "the sensor's address on its bus"),
    *(Register(FLOAT_BASE + 2 * i, Type.F32, name, f"{name} ({unit})" if unit else name, group)
      for i, (name, group, _, unit) in enumerate(_MEASURED)),
    *(Register(INT_BASE + 2 * i, Type.I32, f"{name}_scaled",
               f"{name} × {scale}" + (f" ({unit})" if unit else ""), group, scale)
      for i, (name, group, scale, unit) in enumerate(_MEASURED)),
    # The alarms (docs/alarms.md, the bits themselves in discrete inputs and coils):
    # after the values' blocks, so that nothing there moved when they came.
    Register(ALARM_BASE, Type.U16, "alarm_count", "alarms of this sensor, its "
             "communication alarm included: the discrete inputs and coils 0 to count - 1"),
    Register(ALARM_BASE + 1, Type.U16, "alarms_active", "how many are active"),
    Register(ALARM_BASE + 2, Type.U16, "alarms_unacked", "how many wait for an "
             "acknowledgement"),
    Register(ALARM_BASE + 3, Type.MASK, "alarm_active_mask", "active alarms: word "
             f"{ALARM_BASE + 3} + k holds alarms 16k to 16k + 15, bit b of it alarm 16k + b "
             f"(discrete input 16k + b); the first {alarms.MASK_BITS} alarms"),
    Register(ALARM_BASE + 3 + alarms.MASK_WORDS, Type.MASK, "alarm_unacked_mask",
             "alarms waiting for an acknowledgement (the coils), as the active mask"),
    *(Register(spec.register.address, _command_type(spec), spec.register.name,
               spec.register.description, command=spec.name, series=spec.series)
      for spec in CATALOGUE.values() if spec.register is not None),
)

#: Contiguous blocks of the map: a read must lie inside one.
BLOCKS: tuple[range, ...] = (range(0, 9), range(FLOAT_BASE, FLOAT_BASE + 2 * len(_MEASURED)),
                             range(INT_BASE, INT_BASE + 2 * len(_MEASURED)),
                             range(ALARM_BASE, ALARM_BASE + alarms.REGISTER_WORDS),
                             range(1000, 1009))
BY_ADDRESS: Mapping[int, Register] = {r.address: r for r in REGISTERS}
IMAGE_WORDS = BLOCKS[-1].stop

#: The command registers, with the catalogue rows they are made of.
COMMANDS: Mapping[int, CommandSpec] = {
    spec.register.address: spec for spec in CATALOGUE.values() if spec.register is not None}


def command_args(spec: CommandSpec, words: Sequence[int]) -> dict[str, Any] | None:
    """The arguments a write of ``spec``'s register carries, or ``None`` for a bad
    value: 1 runs a command without arguments, a choice is its code, an angle a
    float32."""
    assert spec.register is not None
    name = spec.argument
    if name is None:
        return {} if words[0] == 1 else None
    if _command_type(spec) is Type.F32:
        # The float32 a client wrote for 99.9 is 99.90000153: the decimal it stands for
        # is what the command gets (the command rounds it to the sensor's resolution,
        # so a half such as 0.35, 0.3499999940 as float32, stays one).
        value = shortest_float32(struct.unpack(">f", struct.pack(">HH", *words))[0])
        return {name: value} if math.isfinite(value) else None
    choices = {code: choice for choice, code in spec.register.codes.items()}
    return {name: choices[words[0]]} if words[0] in choices else None


def inside_a_value(address: int) -> bool:
    """Whether ``address`` is the second word of a 32-bit command register (1005 of
    the float at 1004): a write starting there writes half a value, which is a bad
    value (exception 03, as a one-word write to 1004 is), not a missing address.  The
    measured values are read-only, whichever of their words a write names (02)."""
    return any(r.address < address < r.address + r.type.words
               for r in REGISTERS if r.command is not None)


def block_of(start: int, count: int) -> range | None:
    """The block a read of ``count`` registers from ``start`` lies in, if any."""
    for block in BLOCKS:
        if start in block:
            return block if start + count <= block.stop else None
    return None


def _pack(reg: Register, value: float | int | None) -> bytes:
    """A register's bytes, big-endian, high word first; ``None`` is "not measured"."""
    if reg.type is Type.F32:
        return NAN32 if value is None else struct.pack(">f", value)
    if reg.type is Type.I32:
        if value is None or not math.isfinite(value):
            return struct.pack(">i", INT32_MIN)
        scaled = round(value * reg.scale)
        return struct.pack(">i", max(INT32_MIN + 1, min(2**31 - 1, scaled)))
    if reg.type is Type.U32:
        return struct.pack(">I", int(value or 0) & 0xFFFFFFFF)
    return struct.pack(">H", int(0 if value is None else value) & 0xFFFF)


def _measured_values(reading: Reading | None) -> dict[str, float]:
    return field_values(reading) if reading is not None else {}


class SensorImage:
    """One sensor's map as bytes."""

    def __init__(self, series: Series, protocol: WireProtocol, address: int,
                 stale_after_ms: float) -> None:
        self.series = series
        self.protocol = protocol
        self.address = address
        self.stale_after_ms = stale_after_ms
        self._words = bytearray(2 * IMAGE_WORDS)
        self.has_reading = False
        self._unpacked: Reading | None = None
        self._pack_reading(None)

    @property
    def words(self) -> bytearray:
        """The whole image, the latest reading's values packed."""
        if self._unpacked is not None:
            reading, self._unpacked = self._unpacked, None
            self._pack_reading(reading)
        return self._words

    def set_reading(self, reading: Reading | None) -> None:
        """A new reading: packed when the image is next read."""
        if reading is None:
            self._unpacked = None
            self._pack_reading(None)
        else:
            self._unpacked = reading
        self.has_reading = reading is not None

    def _pack_reading(self, reading: Reading | None) -> None:
        values = _measured_values(reading)
        measures = CAPABILITIES[self.series].groups
        for reg in REGISTERS:
            if reg.group is None:
                continue
            name = reg.name.removesuffix("_scaled")
            value = values.get(name) if reg.group in measures else None
            self._words[2 * reg.address: 2 * (reg.address + reg.type.words)] = _pack(reg, value)

    def set_alarms(self, words: bytes) -> None:
        """The alarm registers (``alarms.UnitAlarms.registers``), at a transition."""
        self._words[2 * ALARM_BASE: 2 * ALARM_BASE + len(words)] = words

    def refresh_status(self, snap: Snapshot) -> None:
        bits = 0
        if snap.online:
            bits |= 1 << STATUS_BITS["online"]
        # Stale means "these values are old", whether or not the sensor is still online:
        # a PLC that checks this bit alone must not trust the values of a dead sensor.
        if snap.age_ms is None or snap.age_ms > self.stale_after_ms:
            bits |= 1 << STATUS_BITS["stale"]
        if snap.busy:
            bits |= 1 << STATUS_BITS["busy"]
        if snap.streaming:
            bits |= 1 << STATUS_BITS["streaming"]
        if snap.reading is None:
            bits |= 1 << STATUS_BITS["no_reading"]
        age = 65535 if snap.age_ms is None else min(65535, int(snap.age_ms))
        self._words[0:18] = struct.pack(">HHIIHHH", bits, age, snap.seq & 0xFFFFFFFF,
                                       snap.errors & 0xFFFFFFFF, self.series.value,
                                       self.protocol.value, self.address)

    def refresh_commands(self, snap: Snapshot, known: KnownSettings) -> None:
        """The command block: the settings as far as the gateway knows them (a
        ``busy_with`` outlives the busy period it names: not past it)."""
        if not snap.busy:
            known = replace(known, busy_with=None)
        for address, spec in COMMANDS.items():
            reg, row = BY_ADDRESS[address], spec.register
            assert row is not None
            shown: str | float | bool | None = getattr(known, row.setting) if row.setting \
                else known.busy_with == spec.name  # (1 while it runs, or 0)
            if isinstance(shown, str) or (shown is None and reg.type is Type.U16):
                shown = row.codes.get(shown or "", row.unknown)
            self._words[2 * address: 2 * (address + reg.type.words)] = _pack(reg, shown)


#: Unit 255: the gateway's own diagnostics, one block of ``DIAG_STRIDE`` registers per
#: bus in config order (bus i from address i × DIAG_STRIDE).  Read-only.
DIAG_UNIT = 255
DIAG_STRIDE = 10
DIAG_REGISTERS: tuple[tuple[int, Type, str, str, float], ...] = (
    # offset, type, stats key, content, scale
    (0, Type.U32, "transactions", "transactions done", 1),
    (2, Type.U32, "errors", "errors of every kind", 1),
    (4, Type.U32, "busy_ms", "time the line spent in exchanges, ms (difference two reads "
     "for the utilisation of a window)", 1),
    (6, Type.U16, "transactions_per_s", "transactions/s over the last 5 s, × 10", 10),
    (7, Type.U16, "utilisation", "time in exchanges ÷ elapsed since start, × 10000", 10000),
    (8, Type.U16, "port_open", "1 when the port is open", 1),
    (9, Type.U16, "queue_depth", "commands and reads waiting", 1),
)


def diagnostics_image(buses: Sequence[BusStats]) -> bytes:
    """Unit 255's registers for the buses' stats (``BusMaster.bus_stats``)."""
    out = bytearray()
    for bus in buses:
        block = bytearray(2 * DIAG_STRIDE)
        for offset, kind, key, _, scale in DIAG_REGISTERS:
            value = getattr(bus, key)
            if key == "errors":
                value = sum(value.values())
            raw = min(round(float(value) * scale), 0xFFFF if kind is Type.U16 else 2**32 - 1)
            fmt = ">H" if kind is Type.U16 else ">I"
            struct.pack_into(fmt, block, 2 * offset, raw)
        out += block
    return bytes(out)


def markdown() -> str:
    """``docs/register-map.md``."""
    lines = [
        "# Modbus TCP register map",
        "",
        "Generated from `imu_gateway/frontends/modbus/map.py` by "
        "`python -m imu_gateway.frontends.modbus.map`; do not edit by hand.",
        "",
        "One map per sensor, addressed by its `unit_id`. Protocol addresses, 0-based. "
        "FC03 and FC04 read the same values. 32-bit values are big-endian, high word "
        "first (ABCD). A value the series does not measure, or that has none now, reads "
        "NaN (f32) or -2147483648 (i32). `tilt`, `tilt_direction` and `vibration` are "
        "derived from the measured values (docs/alarms.md, \"Derived values\"). A read "
        "must lie inside one block "
        f"({', '.join(f'{b.start}-{b.stop - 1}' for b in BLOCKS)}); other addresses answer "
        "exception 02.",
        "",
        "| address | type | name | content | series |",
        "|---|---|---|---|---|",
    ]
    for reg in REGISTERS:
        span = str(reg.address) if reg.type.words == 1 else \
            f"{reg.address}-{reg.address + reg.type.words - 1}"
        if reg.group is not None:
            who = ", ".join(s.name for s in Series if reg.group in CAPABILITIES[s].groups)
        else:
            who = "all" if reg.series == frozenset(Series) else \
                ", ".join(s.name for s in Series if s in reg.series)
        lines.append(f"| {span} | {reg.type.value[1]} | `{reg.name}` | {reg.description} | "
                     f"{who} |")
    lines += [
        "",
        "Writes (FC06, FC16) go to the command registers 1000-1008 only, one command per "
        "request (a float takes both of its registers in one FC16). The answer is sent "
        "after the sensor acknowledged.",
        "",
        "| exception | when |",
        "|---|---|",
        "| 01 | writes not allowed (`allow_writes: false`), or a function code other than "
        "01, 02, 03, 04, 05, 06, 16, 43 (MEI 14) |",
        "| 02 | an address outside the map, a read across blocks, a command this series "
        "or protocol lacks |",
        "| 03 | a quantity outside 1-125 (read) or 1-123 (write), a bad value, half a "
        "float (one register of 1004-1007, or a write starting at 1005 or 1007) |",
        "| 04 | the sensor answered \"failure\"; or a write was sent but its answer was lost "
        "(`unconfirmed`: read the register back before writing again; it is never sent "
        "twice) |",
        "| 06 | the sensor is busy (save or calibration running) |",
        "| 0A | an unknown unit id |",
        "| 0B | the sensor did not answer; or a read of measured values before the first "
        "reading |",
        "",
        *alarms.markdown(),
        f"## Unit {DIAG_UNIT}: gateway diagnostics",
        "",
        f"One block of {DIAG_STRIDE} registers per bus, in the order of the config file "
        f"(bus *i* starts at *i* × {DIAG_STRIDE}). Read-only (FC03/FC04).",
        "",
        "| offset | type | content |",
        "|---|---|---|",
        *(f"| {off if k.words == 1 else f'{off}-{off + 1}'} | {k.value[1]} | {text} |"
          for off, k, _, text, _ in DIAG_REGISTERS),
        "",
        *ident.markdown(),
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown(), end="")
