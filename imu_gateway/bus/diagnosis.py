"""Why a sensor does not answer: what the line shows, put in words for a field engineer.

Sans-IO, part of ``Schedule``.  A sensor that never answers is nearly always one of
four mistakes, each leaving its own trace on the line:

* the wrong baud rate: bytes arrive (a sensor streaming at its own rate, or echoes of
  noise) but never form a frame;
* the wrong address: frames come, from an address nobody configured;
* the wrong protocol: frames come, of the other protocol;
* the wrong series (native): the sensor answers the poll with the shape of another
  series (an AH's 0x59 frame has LEN 0x38, a VG's 0x2F).

Nothing here writes to a sensor: it only reads what the line brings anyway.
"""

from __future__ import annotations

from collections import Counter

from ..model import Series, WireProtocol
from ..protocol import modbus_rtu as rtu
from ..protocol import native
from ..protocol.exchanges import Frame, sender

#: Raw bytes kept to look for frames of the other protocol in (the last of them).
KEPT_BYTES = 512

#: The native combined read's answer shape per series, for telling them apart.
_READ_ALL = native.COMMANDS_BY_NAME["read_all"]
_SHAPES = {series: shape.key for series in Series
           if (shape := _READ_ALL.answer_for(series)) is not None}


def series_by_shape(key: tuple[int, int]) -> list[Series]:
    """The series whose answer to the native poll has this (command, LEN)."""
    return [series for series, shape in _SHAPES.items() if shape == key]


def _label(series: list[Series]) -> str:
    return " or ".join(s.name for s in series)


class Diagnosis:
    """The evidence one line gives; ``cause`` words it for one sensor."""

    def __init__(self, protocol: WireProtocol, port: str) -> None:
        self.protocol = protocol
        self.port = port
        self.recent = bytearray()  # the last KEPT_BYTES bytes in
        self.bytes_in = 0
        self.frames_in = 0
        self.senders: Counter[int] = Counter()  # frames by the address they came from
        self.misfits: dict[str, str] = {}  # sensor -> its answers' misfit, once told

    def received(self, data: bytes) -> None:
        self.bytes_in += len(data)
        self.recent += data
        del self.recent[:-KEPT_BYTES]

    def frame(self, frame: Frame) -> None:
        """Any whole frame of this line's protocol (counted only: which senders are
        strangers is asked when a sensor goes offline, the rare case, not here)."""
        self.frames_in += 1
        self.senders[sender(frame)] += 1

    @staticmethod
    def misfit(frame: Frame, series: Series) -> str | None:
        """What is wrong when a native frame from a sensor has the shape of another
        series' answer to the poll (None: it has not)."""
        if not isinstance(frame, native.NativeFrame):
            return None
        key = (frame.command, len(frame.data) + 4)
        looks_like = series_by_shape(key)
        if not looks_like or series in looks_like:
            return None
        article = "an" if looks_like[0].name[0] in "AI" else "a"
        return (f"answers like {article} {_label(looks_like)} (0x{key[0]:02X}, LEN "
                f"0x{key[1]:02X}); the config says {series.name}: set its series to "
                f"{looks_like[0].name}")

    def first(self, name: str, misfit: str) -> bool:
        """Whether this is the first time a sensor's misfit is told (it is, once)."""
        if name in self.misfits:
            return False
        self.misfits[name] = misfit
        return True

    def cause(self, name: str, address: int, baud: int, configured: set[int]) -> str:
        """The most likely reason sensor ``name`` at ``address`` never answered;
        ``configured``: the addresses of the line's sensors now."""
        if name in self.misfits:
            return f"it {self.misfits[name]}"
        scan = f"`imu-gateway scan --port {self.port}` finds what is on the line"
        other = self._other_protocol()
        if other:
            return f"{other}: wrong protocol? {scan}"
        strangers = [a for a, _ in self.senders.most_common() if a not in configured]
        if strangers:
            found = ", ".join(str(a) for a in strangers[:3])
            return (f"frames come from address {found}, not {address}: wrong address? "
                    f"{scan}")
        if self.bytes_in and not self.frames_in:
            return (f"{self.bytes_in} bytes arrived but never formed a frame at {baud} "
                    f"baud: wrong baud rate? {scan}")
        if not self.bytes_in:
            return (f"nothing came back: check power, wiring (A/B swapped?), the address "
                    f"and the baud rate; {scan}")
        return f"the line answers others, not this address: wrong address? {scan}"

    def _other_protocol(self) -> str:
        """Frames of the protocol this line is not configured for, in the recent bytes."""
        data = bytes(self.recent)
        if self.protocol is WireProtocol.NATIVE:
            frames = rtu.RtuFramer(requests=False).feed(data)
            units = sorted({f.unit for f in frames})
            if len(frames) >= 2:
                return f"Modbus RTU frames arrive (unit {', '.join(map(str, units))})"
        else:
            found = native.NativeFramer().feed(data)
            if len(found) >= 2:
                addresses = sorted({f.address for f in found})
                return (f"native frames arrive (address "
                        f"{', '.join(map(str, addresses))})")
        return ""
