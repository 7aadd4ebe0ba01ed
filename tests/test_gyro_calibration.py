"""A Modbus gyro calibration through the running gateway, against the simulator
(the Modbus document 2.11; docs/protocol-notes.md says what was chosen and why).

The echo of the write says 0 "started" (an unsolicited 1 "done" follows) or 1
"complete".  Complete ends the calibration at once: nothing is busy.  While one runs
the sensor is busy for commands (409 / exception 06), but it is still read: nothing in
the document says it stops answering.

The protocol layer hands the bus master what it needs (``Answer.effect``,
``Effect.read_while_busy``); until the bus master applies both, these tests are
expected to fail (strict: they turn into failures the moment it does, so the marker
cannot outlive the change).
"""

from __future__ import annotations

from typing import Any

import pytest
from support.harness import running, until

from imu_gateway.errors import ErrorKind
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
READING = Motion.from_seed(3).sample(10.0)


def config(path: str) -> dict[str, Any]:
    return {"gateway_id": "test", "buses": [{
        "name": "line", "port": path, "baudrate": FAST, "protocol": "modbus",
        "timeout_ms": 300, "sensors": [{"name": "vg", "series": "VG", "address": 1,
                                        "poll_hz": 20}]}]}


@pytest.mark.anyio
async def test_calibration_answered_complete_is_over_at_once() -> None:
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=hold(READING),
                     gyro_cal_duration=0.0)
    with simulated([vg]) as line:
        async with running(config(line.path)) as gw:
            await until(lambda: gw.cache.snapshot("vg").seq >= 1)
            result = await gw.command("vg", "calibrate_gyro")
            assert result.ok and result.answer == {"value": 1}  # 1 = complete
            assert not gw.cache.snapshot("vg").busy
            assert gw.cache.settings("vg").busy_with is None
            again = await gw.command("vg", "set_zero_type", {"type": "relative"})
            assert again.ok, again  # not refused as busy


@pytest.mark.anyio
async def test_calibration_under_way_is_busy_for_commands_but_still_read() -> None:
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=hold(READING),
                     gyro_cal_duration=1.5)
    with simulated([vg]) as line:
        async with running(config(line.path)) as gw:
            await until(lambda: gw.cache.snapshot("vg").seq >= 1)
            result = await gw.command("vg", "calibrate_gyro")
            assert result.ok and result.answer == {"value": 0}  # 0 = started
            assert gw.cache.snapshot("vg").busy
            assert gw.cache.settings("vg").busy_with == "calibrate_gyro"
            refused = await gw.command("vg", "save")
            assert refused.kind is ErrorKind.BUSY
            seq = gw.cache.snapshot("vg").seq
            await until(lambda: gw.cache.snapshot("vg").seq >= seq + 5, 1.0)
            assert gw.cache.snapshot("vg").busy  # still calibrating, and read
            await until(lambda: not gw.cache.snapshot("vg").busy, 5.0)  # "done"
            assert gw.cache.settings("vg").busy_with is None
            assert (await gw.command("vg", "set_zero_type", {"type": "absolute"})).ok
