"""docs/config-reference.md is generated from the config schema and kept up to date."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from pydantic import BaseModel
from support import ROOT

from imu_gateway.config import (
    BusConfig,
    CaptureConfig,
    GatewayConfig,
    HttpConfig,
    ModbusConfig,
    MqttConfig,
    OpcUaConfig,
    SensorConfig,
    SparkplugConfig,
    config_from_dict,
)
from imu_gateway.config.schema import AlarmConfig, HttpToken, HttpUser, ModbusTlsConfig
from imu_gateway.tools import config_reference as ref

DOC = ROOT / "docs" / "config-reference.md"
MODELS = (GatewayConfig, BusConfig, SensorConfig, AlarmConfig, ModbusConfig, ModbusTlsConfig,
          MqttConfig, SparkplugConfig, HttpConfig, HttpToken, HttpUser, OpcUaConfig,
          CaptureConfig)


def test_config_reference_document_is_up_to_date() -> None:
    assert DOC.read_text() == ref.markdown(), (
        "docs/config-reference.md is out of date: run scripts/config-reference")


def test_every_section_is_in_the_document() -> None:
    assert {model for _, model, _ in ref.SECTIONS} == set(MODELS)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__)
def test_every_key_has_a_description_and_a_row(model: type[BaseModel]) -> None:
    rows = ref.table(model)
    for key, field in model.model_fields.items():
        assert field.description, f"{model.__name__}.{key} has no description"
        assert sum(row.startswith(f"| `{key}` |") for row in rows) == 1


def _rows(section: str) -> dict[str, tuple[str, str, str]]:
    """The document's table under ``## `section` ``: key → (type, default, rule)."""
    text = DOC.read_text()
    body = text.split(f"## `{section}`\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in body.splitlines():
        cells = re.split(r"(?<!\\) \| ", line.strip("| "))
        if line.startswith("| `") and len(cells) == 4:
            rows[cells[0].strip("`")] = (cells[1], cells[2], cells[3])
    return rows


def test_defaults_shown_are_the_defaults_a_minimal_config_gets() -> None:
    config = config_from_dict({
        "buses": [{"name": "a", "port": "/dev/ttyS0", "protocol": "native",
                   "sensors": [{"name": "s", "series": "AH"}]}],
        "modbus": {}, "mqtt": {}, "http": {}}, env={})
    bus, sensor = config.buses[0], config.buses[0].sensors[0]
    assert config.modbus is not None and config.mqtt is not None and config.http is not None
    checks = {
        "buses[]": {"baudrate": str(bus.baudrate), "retries": str(bus.retries),
                    "rs485": "false"},
        "buses[].sensors[]": {"poll_hz": "10", "stream_hz": "0",
                              "stale_after_ms": str(sensor.stale_after_ms)},
        "modbus": {"listen": f"`{config.modbus.listen}`",
                   "max_connections": str(config.modbus.max_connections)},
        "mqtt": {"url": f"`{config.mqtt.url}`", "base_topic": f"`{config.mqtt.base_topic}`",
                 "queue_size": str(config.mqtt.queue_size), "retain": "true"},
        "http": {"listen": f"`{config.http.listen}`"},
    }
    for section, expected in checks.items():
        rows = _rows(section)
        for key, default in expected.items():
            assert rows[key][1] == default, (section, key)


def test_type_names() -> None:
    rows = _rows("buses[]")
    assert rows["timeout_ms"][0] == "integer or null"
    assert rows["rs485"][0] == "boolean"
    assert _rows("modbus")["allow_from"][0] == "list of networks"
    assert _rows("mqtt")["deadband"][0] == "map"
    assert _rows("buses[].sensors[]")["poll_hz"][0] == "number"


def test_a_pipe_in_a_rule_does_not_break_the_table() -> None:
    assert ref._cell("native | modbus") == "native \\| modbus"


def test_module_prints_the_document() -> None:
    out = subprocess.run([sys.executable, "-m", "imu_gateway.tools.config_reference"],
                         capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout == ref.markdown()
