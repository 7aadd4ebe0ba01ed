"""The Modbus TCP register map table against the layout written out here, and its
generated document."""

from __future__ import annotations

from support import ROOT

from imu_gateway.frontends.modbus import map as mm
from imu_gateway.normalise import FIELD_NAMES

DOC = ROOT / "docs" / "register-map.md"


def test_register_map_document_is_up_to_date() -> None:
    assert DOC.read_text() == mm.markdown(), (
        "docs/register-map.md is out of date: run "
        "`python -m imu_gateway.frontends.modbus.map > docs/register-map.md`")


def test_status_block_is_as_specified() -> None:
    layout = [(r.address, r.type, r.name) for r in mm.REGISTERS if r.address < 100]
    assert layout == [
        (0, mm.Type.U16, "status"), (1, mm.Type.U16, "age_ms"), (2, mm.Type.U32, "seq"),
        (4, mm.Type.U32, "errors"), (6, mm.Type.U16, "series"), (7, mm.Type.U16, "protocol"),
        (8, mm.Type.U16, "bus_address"),
    ]


def test_measured_values_in_the_specified_order_and_scales() -> None:
    floats = [r for r in mm.REGISTERS if mm.FLOAT_BASE <= r.address < mm.INT_BASE]
    ints = [r for r in mm.REGISTERS if mm.INT_BASE <= r.address < mm.ALARM_BASE]
    assert [r.name for r in floats] == list(FIELD_NAMES)
    # the sixteen measured values where they always were, the derived appended after them
    assert [r.address for r in floats] == list(range(100, 138, 2))
    assert [r.address for r in ints] == list(range(200, 238, 2))
    assert [r.name for r in floats[16:]] == ["tilt", "tilt_direction", "vibration"]
    assert [r.scale for r in ints] == [100] * 3 + [10000] * 3 + [100] * 3 + [100000] * 3 + \
        [1000000] * 4 + [100, 100, 10000]


def test_alarm_registers_after_the_values_as_specified() -> None:
    alarms = [(r.address, r.type.words, r.name) for r in mm.REGISTERS
              if 300 <= r.address < mm.COMMAND_BASE]
    assert alarms == [(300, 1, "alarm_count"), (301, 1, "alarms_active"),
                      (302, 1, "alarms_unacked"), (303, 4, "alarm_active_mask"),
                      (307, 4, "alarm_unacked_mask")]
    assert range(300, 311) in mm.BLOCKS


def test_command_registers_as_specified() -> None:
    commands = {r.address: (r.type, r.command) for r in mm.REGISTERS if r.command}
    assert commands == {
        1000: (mm.Type.U16, "set_zero_type"), 1001: (mm.Type.U16, "save"),
        1002: (mm.Type.U16, "calibrate_gyro"), 1003: (mm.Type.U16, "clear_heading"),
        1004: (mm.Type.F32, "set_relative_heading"), 1006: (mm.Type.F32, "set_declination"),
        1008: (mm.Type.U16, "mag_calibration"),
    }


def test_blocks_cover_exactly_the_registers() -> None:
    covered = {a for r in mm.REGISTERS for a in range(r.address, r.address + r.type.words)}
    assert covered == {a for block in mm.BLOCKS for a in block}
