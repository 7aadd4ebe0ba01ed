"""The MQTT front end's pure parts: its topics, which of them it retains, and the rules
of when a state is sent (``min_interval_ms`` and the deadbands).

No client, no loop, no clock: the MQTT client (``client.py``) calls these with what it
knows, and the tests check them on values alone.  (The messages and counters are the
transport's: ``imu_gateway/mqtt_link/message.py``.)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ...alarms import COMMUNICATION
from ...config import MqttConfig, SensorConfig
from ...normalise import MEASURED_FIELDS

# A sensor's topics beside its state: what the gateway knows of its settings, and the
# state again for Home Assistant (throttled apart); the gateway's counters.
SETTINGS_LEAF, HA_LEAF, DIAGNOSTICS_LEAF = "settings", "ha", "diagnostics"
# An alarm's state, retained: ``{prefix}/{sensor}/alarm/{alarm}``; where it is
# acknowledged: that topic with ``/ack`` appended.
ALARM_LEAF, ACK_LEAF = "alarm", "ack"
CONTROL_QOS = 1  # status, availability, discovery, results: small and must arrive
ONLINE, OFFLINE = b"online", b"offline"  # the status and availability payloads


@dataclass(frozen=True, slots=True)
class Topics:
    """Every topic of one gateway: ``{base}/{gateway_id}/…`` and the discovery ones."""

    base: str
    gateway_id: str
    discovery_prefix: str

    @classmethod
    def of(cls, config: MqttConfig, gateway_id: str) -> Topics:
        return cls(config.base_topic, gateway_id, config.discovery_prefix)

    @property
    def prefix(self) -> str:
        return f"{self.base}/{self.gateway_id}"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    @property
    def instance(self) -> str:
        """The claim of the gateway process holding this id (``identity.py``)."""
        return f"{self.prefix}/instance"

    def client(self, client_id: str) -> str:
        """The claim of the gateway process using an MQTT client id (``identity.py``);
        the client id's ``/ + #`` become ``_``."""
        safe = client_id.replace("/", "_").replace("+", "_").replace("#", "_")
        return f"{self.base}/_clients/{safe}"

    def of_gateway(self, gateway_id: str) -> Topics:
        return Topics(self.base, gateway_id, self.discovery_prefix)

    @property
    def captures(self) -> str:
        """Each new capture, announced (not retained: ``GET /api/v1/captures`` lists them)."""
        return f"{self.prefix}/captures"

    @property
    def diagnostics(self) -> str:
        return f"{self.prefix}/{DIAGNOSTICS_LEAF}"

    def sensor(self, sensor: str, leaf: str) -> str:
        return f"{self.prefix}/{sensor}/{leaf}"

    def alarm(self, sensor: str, alarm: str) -> str:
        return f"{self.prefix}/{sensor}/{alarm_leaf(alarm)}"

    def alarm_ack(self, sensor: str, alarm: str) -> str:
        return f"{self.alarm(sensor, alarm)}/{ACK_LEAF}"

    def object_id(self, sensor: str, field_name: str) -> str:
        # Home Assistant's object ids allow [a-zA-Z0-9_-]; a gateway id may hold dots.
        return f"{self.gateway_id}_{sensor}_{field_name}".replace(".", "_")

    def discovery(self, sensor: str, field_name: str) -> str:
        return f"{self.discovery_prefix}/sensor/{self.object_id(sensor, field_name)}/config"


def alarm_leaf(alarm: str) -> str:
    return f"{ALARM_LEAF}/{alarm}"


def alarm_names(sensor: SensorConfig) -> tuple[str, ...]:
    """A sensor's alarms in config order, its communication alarm last (as
    ``GatewayLike.alarm_states`` lists them)."""
    return (*(alarm.name for alarm in sensor.alarms), COMMUNICATION)


def retained_leaves(config: MqttConfig,
                    sensors: Mapping[str, SensorConfig]) -> dict[str, frozenset[str]]:
    """Per sensor, the leaves of ``{prefix}/{sensor}/…`` the gateway retains: the
    availability, the known settings and each alarm's state, Home Assistant's state
    with discovery, and the state and per-field values when ``retain`` is on."""
    out = {}
    for name, sensor in sensors.items():
        leaves = {"availability", SETTINGS_LEAF, *map(alarm_leaf, alarm_names(sensor))}
        if config.homeassistant_discovery:
            leaves.add(HA_LEAF)
        if config.retain:
            leaves.add("state")
            if config.per_field_topics:
                leaves.update(MEASURED_FIELDS[sensor.series])
        out[name] = frozenset(leaves)
    return out


def within_deadband(values: Mapping[str, float], sent: Mapping[str, float] | None,
                    deadbands: Mapping[str, float]) -> bool:
    """Is a reading with field ``values`` too close to the one last ``sent`` to send?
    Only when every field that has a deadband moved by no more than it (a reading
    with none of those fields, or nothing sent yet, always goes)."""
    if not deadbands or sent is None:
        return False
    moved = [abs(values[f] - sent[f]) > band
             for f, band in deadbands.items() if f in values and f in sent]
    return bool(moved) and not any(moved)


def send_delay(sent_at: float, min_interval_s: float, now: float) -> float:
    """How long a new state must wait for ``min_interval_ms`` (0: it goes now)."""
    return max(0.0, sent_at + min_interval_s - now)
