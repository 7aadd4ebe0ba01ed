"""The OPC UA address space, as rows: the server builds it from them, and
docs/opcua.md is generated from them.

    Objects/IMU Gateway/{gateway_id}/
        Sensors/{sensor}/               an object per sensor
            Angles/pitch …              AnalogItemType (Double), per value group the
            Acceleration/ …             series measures, with EngineeringUnits (UNECE)
            AngularRate/ … MagneticField/ … Quaternion/ …   and EURange
            Tilt/ … Vibration/ …        (derived: docs/alarms.md)
            Status, Sequence, Errors, Series, Protocol, Address
            (methods: the catalogue's commands, with ``allow_commands``)
        Buses/{bus}/                    the line's counters

Node ids are strings in the gateway's namespace, ``{gateway_id}.Sensors.{sensor}.{path}``,
so a client's configuration survives a restart and a reordered config.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ...cache import Snapshot, Status
from ...model import Group
from ...stats import BusStats

NAMESPACE = "urn:imu-gateway"
#: OPC UA's namespace of UNECE unit codes (OPC 10000-8, EUInformation)
UNECE = "http://www.opcfoundation.org/UA/units/un/cefact"


@dataclass(frozen=True, slots=True)
class Unit:
    """A UNECE Recommendation 20 unit: its common code, symbol and name."""

    code: str
    symbol: str
    name: str

    @property
    def unit_id(self) -> int:
        """OPC UA's UnitId: the code's ASCII bytes, big-endian, in an Int32."""
        out = 0
        for char in self.code:
            out = (out << 8) | ord(char)
        return out


#: The unit of each value group (none for the quaternion).
UNITS: dict[Group, Unit | None] = {
    Group.ANGLES: Unit("DD", "°", "degree [unit of angle]"),
    Group.ACCEL: Unit("K40", "gn", "standard acceleration of free fall"),
    Group.GYRO: Unit("E96", "°/s", "degree per second"),
    Group.MAG: Unit("76", "Gs", "gauss"),
    Group.QUATERNION: None,
    Group.TILT: Unit("DD", "°", "degree [unit of angle]"),
    Group.VIBRATION: Unit("K40", "gn", "standard acceleration of free fall"),
}

SensorValue = str | float | int | None


@dataclass(frozen=True, slots=True)
class SensorVar:
    """A sensor's status or identity variable: name, OPC UA type, what it says."""

    name: str
    datatype: str  # an asyncua VariantType name
    description: str
    value: Callable[[Snapshot], SensorValue]


SENSOR_VARS = (
    SensorVar("Status", "String", "ok, stale or offline", lambda s: s.status.value),
    SensorVar("Sequence", "UInt64", "the sample's sequence number (one more per reading)",
              lambda s: s.seq),
    SensorVar("Errors", "UInt64", "timeouts, bad checksums and bad frames so far",
              lambda s: s.errors),
)


@dataclass(frozen=True, slots=True)
class IdentityVar:
    """What a sensor is, from the config: name, OPC UA type, what it says."""

    name: str
    datatype: str
    description: str


IDENTITY_VARS = (
    IdentityVar("Series", "String", "IMU, VG, AH or MINS"),
    IdentityVar("Protocol", "String", "native or modbus"),
    IdentityVar("Address", "UInt16", "the sensor's address on its bus"),
)


@dataclass(frozen=True, slots=True)
class BusVar:
    """A bus counter: name, OPC UA type, what it says, its value in ``BusStats``."""

    name: str
    datatype: str
    description: str
    value: Callable[[BusStats], str | float | int | bool]


BUS_VARS = (
    BusVar("Port", "String", "the serial port", lambda b: b.port),
    BusVar("Baudrate", "UInt32", "its baud rate", lambda b: b.baudrate),
    BusVar("Protocol", "String", "native or modbus", lambda b: b.protocol),
    BusVar("PortOpen", "Boolean", "the port is open", lambda b: b.port_open),
    BusVar("Transactions", "UInt64", "exchanges done", lambda b: b.transactions),
    BusVar("Errors", "UInt64", "errors of every kind", lambda b: sum(b.errors.values())),
    BusVar("TransactionsPerSecond", "Double", "over the last 5 s",
           lambda b: b.transactions_per_s),
    BusVar("Utilisation", "Double", "time in exchanges ÷ elapsed", lambda b: b.utilisation),
    BusVar("QueueDepth", "UInt32", "commands and reads waiting", lambda b: b.queue_depth),
)

#: How a sensor's status shows as the values' StatusCode.
QUALITY = {
    Status.OK: "Good",
    Status.STALE: "UncertainLastUsableValue",
    Status.OFFLINE: "BadCommunicationError",
}
NEVER_READ = "BadNoCommunication"


def quality(snap: Snapshot) -> str:
    """The StatusCode name of a sensor's values now."""
    return NEVER_READ if snap.reading is None else QUALITY[snap.status]
