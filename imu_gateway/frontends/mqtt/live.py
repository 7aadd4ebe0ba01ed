"""A reload that changed the sensors, on the same MQTT connection (docs/mqtt.md,
"A reload"): what the broker's retained messages must become, worked out on values.

Restarting the client would drop the connection, and Home Assistant would see every
entity go unavailable for a moment.  Instead the client keeps its session and says
only what changed:

* the discovery configs of entities that are gone are swept (an empty retained
  message: Home Assistant removes the entity), first, so that no entity is left
  reading a topic about to be cleared;
* the configs that are new, or whose payload changed (a sensor's alarms, its name
  and so its topics), are published;
* the retained topics this gateway no longer publishes (a removed sensor's state,
  availability, settings and alarms; a removed alarm's state) are cleared.

The connection's own sweep (``sweep.py``) works from the same sets after each
connect, so what a reload said while the broker was away is put right at the next.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any

from .topics import SETTINGS_LEAF, Topics

#: The leaves sent through the control queue (``send_control``); the others (the
#: state, Home Assistant's, the per-field values) go through the outbox with the
#: states.  A clearing goes the way its topic's messages go: behind any still waiting
#: there, so that none sent before the reload lands after its clearing and retains
#: it again.  (An alarm's leaf, ``alarm/{name}``, goes through the control queue.)
CONTROL_LEAVES = frozenset({"availability", SETTINGS_LEAF})


@dataclass(frozen=True)
class SensorSetChange:
    """What a new sensor set asks of the broker's retained messages."""

    swept: tuple[str, ...]  # discovery topics no longer published: emptied
    configs: tuple[str, ...]  # discovery topics new or changed: published
    cleared: tuple[str, ...]  # retained sensor topics no longer published: emptied
    announced: tuple[str, ...]  # sensors added or changed: their retained topics anew

    @property
    def empty(self) -> bool:
        return not (self.swept or self.configs or self.cleared or self.announced)

    def summary(self) -> str:
        """For the log: ``+12 discovery configs, -3 swept, 9 retained topics cleared``."""
        return (f"{len(self.configs)} discovery configs published, {len(self.swept)} swept, "
                f"{len(self.cleared)} retained topics cleared, sensors announced anew: "
                f"{', '.join(self.announced) or 'none'}")


def sensor_set_change(topics: Topics,
                      discovery: tuple[Mapping[str, Any], Mapping[str, Any]],
                      leaves: tuple[Mapping[str, Collection[str]], Mapping[str, Collection[str]]],
                      sensors: tuple[Mapping[str, object], Mapping[str, object]]
                      ) -> SensorSetChange:
    """From the (old, new) discovery configs (topic -> payload), retained leaves (per
    sensor) and sensor configs (by name, compared for equality)."""
    old_discovery, new_discovery = discovery
    old_leaves, new_leaves = leaves
    old_sensors, new_sensors = sensors
    cleared = [topics.sensor(name, leaf)
               for name, was in old_leaves.items()
               for leaf in sorted(set(was) - set(new_leaves.get(name, ())))]
    return SensorSetChange(
        swept=tuple(t for t in old_discovery if t not in new_discovery),
        configs=tuple(t for t, payload in new_discovery.items()
                      if old_discovery.get(t) != payload),
        cleared=tuple(cleared),
        announced=tuple(name for name, sensor in new_sensors.items()
                        if old_sensors.get(name) != sensor))


def through_outbox(topics: Topics, topic: str) -> bool:
    """Whether a retained sensor topic is sent with the states (through the outbox)."""
    leaf = topic.removeprefix(topics.prefix + "/").partition("/")[2]
    return "/" not in leaf and leaf not in CONTROL_LEAVES
