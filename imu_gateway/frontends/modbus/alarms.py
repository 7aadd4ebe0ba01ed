"""A sensor unit's alarms over Modbus TCP (docs/alarms.md, "In Modbus TCP").

One bit per alarm, in the order of ``GatewayLike.alarm_states()`` (the sensor's
configured alarms in config order, its ``communication`` alarm last), from address 0:

- discrete inputs (FC 02): 1 while the alarm is active;
- coils (FC 01): 1 while it waits for an acknowledgement; FC 05 writing 1 (0xFF00)
  acknowledges it.

The map's alarm registers (``map.ALARM_BASE``) hold the count and the bits as masks.
The bits change only at a transition (the cache's ``ALARM`` event), so a sample costs
this nothing, and a read is a slice as every other read of the map is.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

from ...alarms import AlarmState
from ...modbus_codes import ILLEGAL_ADDRESS, ILLEGAL_VALUE

READ_COILS, READ_DISCRETE, WRITE_COIL = 0x01, 0x02, 0x05
MAX_BITS = 2000  # the most bits one FC 01/02 may ask for (Modbus Application Protocol)
COIL_ON, COIL_OFF = 0xFF00, 0x0000
#: The masks in the alarm registers carry this many alarms (four words each); a
#: sensor with more has the rest in its discrete inputs and coils only.
MASK_BITS = 64
MASK_WORDS = MASK_BITS // 16
#: count, active, unacknowledged, the active mask, the unacknowledged mask
REGISTER_WORDS = 3 + 2 * MASK_WORDS


class UnitAlarms:
    """One sensor unit's alarms as bits, kept as each transition comes: two integers,
    bit i of each alarm i's (Python's integers: as many alarms as configured)."""

    def __init__(self, states: Sequence[AlarmState]) -> None:
        self.names = tuple(s.name for s in states)
        self._index = {name: i for i, name in enumerate(self.names)}
        self.active = 0  # the discrete inputs: 1 while active
        self.unacked = 0  # the coils: 1 while unacknowledged
        for state in states:
            self.update(state)

    def __len__(self) -> int:
        return len(self.names)

    def update(self, state: AlarmState) -> None:
        """The alarm's state after a transition."""
        i = self._index.get(state.name)
        if i is None:  # (every alarm of the sensor is known from the start)
            return
        bit = 1 << i
        self.active = self.active | bit if state.active else self.active & ~bit
        self.unacked = self.unacked & ~bit if state.acked else self.unacked | bit

    def bits(self, function: int, start: int, count: int) -> bytes:
        """The answer's data of an FC 01/02 read inside the alarms: the bits packed
        eight a byte, the first in the lowest bit (the Modbus order: little-endian)."""
        source = self.unacked if function == READ_COILS else self.active
        return ((source >> start) & ((1 << count) - 1)).to_bytes((count + 7) // 8, "little")

    def registers(self) -> bytes:
        """The alarm registers' words (docs/register-map.md): the count, how many are
        active and unacknowledged, then the two masks, each word k holding alarms 16k
        to 16k + 15 (bit b of it: alarm 16k + b)."""
        def mask(bits: int) -> list[int]:
            return [(bits >> (16 * k)) & 0xFFFF for k in range(MASK_WORDS)]

        return struct.pack(f">HHH{2 * MASK_WORDS}H", len(self.names), self.active.bit_count(),
                           self.unacked.bit_count(), *mask(self.active), *mask(self.unacked))


def read(alarms: UnitAlarms, pdu: bytes) -> bytes:
    """The answer to an FC 01 or FC 02 request (checked in the specification's
    order: the quantity, then the addresses)."""
    function = pdu[0]
    if len(pdu) != 5:
        return _exception(function, ILLEGAL_VALUE)
    start, count = struct.unpack_from(">HH", pdu, 1)
    if not 1 <= count <= MAX_BITS:
        return _exception(function, ILLEGAL_VALUE)
    if start + count > len(alarms):
        return _exception(function, ILLEGAL_ADDRESS)
    data = alarms.bits(function, start, count)
    return bytes((function, len(data))) + data


def write(alarms: UnitAlarms, pdu: bytes, acknowledge: Callable[[str], AlarmState]) -> bytes:
    """The answer to an FC 05 request (the client's right to write was checked):
    1 acknowledges the alarm at its address through ``acknowledge(alarm)``, which
    raises ``RequestFailed`` (``nothing_to_acknowledge``); 0 does nothing, so that an
    HMI's momentary button, which writes 1 when pressed and 0 when let go, works."""
    function = pdu[0]
    if len(pdu) != 5:
        return _exception(function, ILLEGAL_VALUE)
    address, value = struct.unpack_from(">HH", pdu, 1)
    if value not in (COIL_ON, COIL_OFF):
        return _exception(function, ILLEGAL_VALUE)
    if address >= len(alarms):
        return _exception(function, ILLEGAL_ADDRESS)
    if value == COIL_ON:
        alarms.update(acknowledge(alarms.names[address]))
    return pdu  # the answer to FC 05 is the request


def _exception(function: int, code: int) -> bytes:
    return bytes((function | 0x80, code))


def markdown() -> list[str]:
    """docs/register-map.md's alarm section."""
    return [
        "## Alarms: discrete inputs and coils",
        "",
        "Each sensor unit has one bit per alarm, from address 0: the sensor's alarms "
        "in config order, its `communication` alarm last (a sensor without configured "
        "alarms has one bit, address 0: `communication`). Register 300 says how many. "
        "The meaning of each state is in docs/alarms.md.",
        "",
        "| addresses | function | content |",
        "|---|---|---|",
        "| 0 to count - 1 | FC 02 read discrete inputs | 1 while the alarm is active "
        "(`active_unacked`, `active_acked`) |",
        "| 0 to count - 1 | FC 01 read coils | 1 while the alarm waits for an "
        "acknowledgement (`active_unacked`, `rtn_unacked`) |",
        "| 0 to count - 1 | FC 05 write single coil | 0xFF00 (1) acknowledges the alarm "
        "(the answer, the request echoed, comes once it is acknowledged); 0x0000 (0) "
        "does nothing (an HMI's momentary button writes it when let go) |",
        "",
        "| exception | when |",
        "|---|---|",
        "| 01 | FC 05 without `allow_writes` (on the TLS port: without the `write` "
        "right; FC 01 and 02 need `read`); FC 15 (write multiple coils) |",
        "| 02 | an address at or beyond the count (a read must end within it) |",
        "| 03 | a quantity outside 1-2000 (FC 01, 02); an FC 05 value other than "
        "0xFF00 and 0x0000; 0xFF00 to an alarm that waits for no acknowledgement "
        "(`normal`, `active_acked`: REST's 409 `nothing_to_acknowledge`) |",
        "",
    ]
