"""A byte-exact sensor simulator: sans-IO sensors (``sensor``), a motion model
(``motion``) and a pseudo-terminal line that honours wire time (``bus``).

It is built on ``imu_gateway.protocol`` and never the other way round.
"""

from .bus import PtyBus, SimulatorThread, simulated
from .motion import Fixed, Motion, hold
from .sensor import Faults, ModbusSensor, NativeSensor, SimSensor, make_sensor

__all__ = [
    "Faults", "Fixed", "ModbusSensor", "Motion", "NativeSensor", "PtyBus", "SimSensor",
    "SimulatorThread", "hold", "make_sensor", "simulated",
]
