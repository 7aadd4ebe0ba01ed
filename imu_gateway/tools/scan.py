"""``imu-gateway scan``: which sensors are on this port, at which rate and address?

The scan itself is ``imu_gateway.bus.scan`` (REST's ``POST /api/v1/scan`` runs the same
one); this module adds what only the command line says.
"""

from __future__ import annotations

import shlex
from collections.abc import Sequence

from ..bus.scan import (
    BAUD_ORDER,
    RESERVED_UNITS,
    Found,
    Prober,
    Progress,
    ReservedUnitAnswers,
    Step,
    Throttle,
    modbus_units,
    plan,
    port_problem,
    scan,
    scan_modbus,
    time_left,
)
from ..model import WireProtocol

__all__ = ["BAUD_ORDER", "Found", "Prober", "Progress", "ReservedUnitAnswers", "Step",
           "Throttle", "modbus_units", "next_time", "plan", "port_problem", "scan",
           "scan_modbus", "time_left"]


def next_time(port: str, found: Sequence[Found], margin_ms: float | None = None) -> str:
    """The command line that would have been enough to find ``found``: its protocols
    and baud rates only (and the reserved units, or the margin, if they were needed)."""
    flags = ["--port", port]
    protocols = [p for p in WireProtocol if any(f.protocol is p for f in found)]
    if len(protocols) == 1:
        flags += ["--protocol", protocols[0].name.lower()]
    for baud in sorted({f.baudrate for f in found}):
        flags += ["--baud", str(baud)]
    if any(f.protocol is WireProtocol.MODBUS and f.address in RESERVED_UNITS for f in found):
        flags.append("--all-addresses")
    if margin_ms is not None:
        flags += ["--margin-ms", f"{margin_ms:g}"]
    return f"next time: imu-gateway scan {shlex.join(flags)}"
