"""The config file (docs/configuration.md): a YAML schema, validated at load.

``load_config(path)`` returns a :class:`GatewayConfig` or raises :class:`ConfigError`,
whose ``problems`` are one line each, ``<yaml path>: <message>``
(``buses[0].sensors[1].series: must be one of IMU, VG, AH, MINS, not "XY"``).  Every
problem in the file is listed, not only the first: field errors from pydantic are
converted in one place (``problems.pydantic_problem``), and the checks that span several
fields (uniqueness, one streaming sensor per bus, what a protocol allows) run on every
part that is valid on its own (``checks.cross_problems``).

The modules import one way: ``fields`` ← ``checks`` ← ``schema`` ← ``problems`` ←
``loading`` (``tests/test_layering.py`` holds it).

Defaults that depend on context are filled in before validation, so the models always
hold final values: a sensor's ``address`` (0 on a native bus, 1 on a modbus bus) and its
``unit_id`` (1, 2, … in document order across the gateway, skipping the ids taken
explicitly).

Each field's ``description`` is its rule for the user: ``docs/config-reference.md`` is
generated from them (``scripts/config-reference``); ``docs/configuration.md`` is the
narrative.
"""

from __future__ import annotations

from .fields import ListenAddress
from .loading import config_from_dict, load_config, load_config_text
from .schema import (
    Broker,
    BusConfig,
    CaptureConfig,
    GatewayConfig,
    HttpConfig,
    ModbusConfig,
    MqttConfig,
    OpcUaConfig,
    SensorConfig,
    SparkplugConfig,
)

__all__ = [
    "Broker",
    "BusConfig",
    "CaptureConfig",
    "GatewayConfig",
    "HttpConfig",
    "ListenAddress",
    "ModbusConfig",
    "MqttConfig",
    "OpcUaConfig",
    "SensorConfig",
    "SparkplugConfig",
    "config_from_dict",
    "load_config",
    "load_config_text",
]
