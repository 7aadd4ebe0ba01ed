"""The procedures' state machines (imu_gateway/procedures.py, docs/wizards.md) in virtual
time: the test is the clock, the sensor and the person; nothing sleeps."""

from __future__ import annotations

import math
from typing import Any

import pytest

from imu_gateway.commands import CommandResult, commands_for
from imu_gateway.errors import ErrorKind, RequestFailed
from imu_gateway.model import Angles, Reading, Series, Vector3, WireProtocol
from imu_gateway.procedures import (
    PROCEDURES,
    SECTORS,
    ChangeConfig,
    CircleTrace,
    ConfigChange,
    Placement,
    Run,
    SendCommand,
    State,
    Wait,
    available,
    validate,
)

NATIVE, MODBUS = WireProtocol.NATIVE, WireProtocol.MODBUS


def start(name: str, args: dict[str, Any] | None = None, series: Series = Series.AH,
          protocol: WireProtocol = NATIVE, now: float = 100.0) -> Run:
    spec, values = validate(name, args, series, commands_for(series, protocol))
    return Run(spec, values, now)


def ok(run: Run, answer: dict[str, Any], now: float) -> None:
    """The driver's side: send what the run asks, and hand back the sensor's answer."""
    action = run.action(now)
    assert isinstance(action, SendCommand), action
    run.sending()
    run.answered(CommandResult("s", action.command, True, answer), now)


def mag(degrees: float, radius: float = 0.2, centre: tuple[float, float] = (0.0, 0.0),
        squash: float = 1.0) -> Reading:
    a = math.radians(degrees)
    return Reading(angles=Angles(0.0, 0.0, degrees),
                   mag=Vector3(centre[0] + radius * math.cos(a),
                               centre[1] + radius * squash * math.sin(a), 0.4))


def test_gyro_counts_down_then_calibrates_and_a_native_one_is_over_when_answered() -> None:
    run = start("gyro_calibration", {"countdown_s": 3.0})
    assert run.action(100.0) == Wait(103.0)
    view = run.to_json(101.0)
    assert (view["step"], view["countdown_s"]) == ("countdown", 2.0)
    assert view["prompt"] == "Keep the sensor absolutely still"
    assert run.action(102.99) == Wait(103.0)  # not a moment early
    assert run.action(103.0) == SendCommand("calibrate_gyro", {})
    run.sending()
    assert run.action(103.1) == Wait(None)  # in flight
    run.answered(CommandResult("s", "calibrate_gyro", True, {"code": 1}), 103.2)
    run.observe(5, None, False, 103.2)  # native: nothing is busy
    assert run.state is State.DONE and run.action(103.3) is None
    assert run.to_json(104.0)["answers"] == {"calibrate_gyro": {"code": 1}}


def test_a_modbus_gyro_calibration_is_busy_until_the_sensor_says_done() -> None:
    run = start("gyro_calibration", {"countdown_s": 0.0}, Series.VG, MODBUS)
    ok(run, {"value": 0}, 100.0)
    run.observe(7, None, True, 100.0)  # the gateway marks it busy
    assert run.state is State.RUNNING and run.to_json(100.0)["step"] == "until_idle"
    assert run.action(105.0) == Wait(112.0)  # its limit: the gateway's 10 s and 2
    run.observe(30, None, True, 105.0)
    assert run.to_json(105.0)["state"] == "running"
    run.observe(31, None, False, 106.5)  # "done"
    assert run.to_json(107)["state"] == "done" and run.to_json(107)["elapsed_s"] == 6.5


def test_a_calibration_still_busy_after_its_limit_fails_as_timeout() -> None:
    run = start("gyro_calibration", {"countdown_s": 0.0}, Series.VG, MODBUS)
    ok(run, {"value": 0}, 100.0)
    run.observe(1, None, True, 100.0)
    assert run.action(112.0) is None
    assert (run.state, run.kind) == (State.FAILED, ErrorKind.TIMEOUT)
    assert run.error == "the sensor was still busy after 12 s"


def test_a_refused_command_fails_the_procedure_with_its_error() -> None:
    run = start("gyro_calibration", {"countdown_s": 0.0})
    run.sending()
    run.answered(CommandResult("s", "calibrate_gyro", False, {}, "s is busy for another 4 s",
                               ErrorKind.BUSY), 100.0)
    view = run.to_json(100.0)
    assert (view["state"], view["kind"]) == ("failed", "busy")
    assert view["error"] == "calibrate_gyro: s is busy for another 4 s"


def test_mag_clears_starts_covers_the_circle_finishes_and_offers_save() -> None:
    run = start("mag_calibration")
    ok(run, {"result": "success"}, 100.0)
    assert run.action(100.0) == SendCommand("mag_calibration", {"action": "start"})
    ok(run, {"result": "success"}, 100.1)
    assert run.to_json(100.1)["step"] == "circle"
    seq = 0
    for degrees in range(0, 180, 5):  # half a circle, off centre and squashed
        seq += 1
        run.observe(seq, mag(degrees, centre=(0.02, 0.0), squash=0.8), False, 100 + seq / 10)
    half = run.to_json(110.0)
    assert half["coverage_percent"] == 50.0 and half["quality"] is None
    assert run.action(110.0) == Wait(None)
    for degrees in range(180, 365, 5):
        seq += 1
        run.observe(seq, mag(degrees, centre=(0.02, 0.0), squash=0.8), False, 100 + seq / 10)
    assert run.action(120.0) == SendCommand("mag_calibration", {"action": "finish"})
    ok(run, {"result": "success"}, 120.0)
    view = run.to_json(120.0)
    assert (view["state"], view["coverage_percent"], view["offers"]) == ("done", 100.0,
                                                                         ["save"])
    assert view["prompt"] == "done: save now, to keep it"
    assert view["quality"]["ellipse_ratio"] == pytest.approx(1 / 0.8, rel=0.01)
    assert view["quality"]["centre_offset_percent"] == pytest.approx(100 * 0.02 / 0.18, rel=0.02)
    assert set(view["answers"]) == {"mag_calibration clear", "mag_calibration start",
                                    "mag_calibration finish"}


def test_the_same_reading_twice_counts_once_and_finish_ends_the_circle_early() -> None:
    run = start("mag_calibration")
    ok(run, {}, 100.0)
    ok(run, {}, 100.0)
    run.observe(1, mag(0), False, 100.1)
    run.observe(1, mag(90), False, 100.2)  # the same seq: not a new reading
    assert run.to_json(100.2)["coverage_percent"] == round(100 / SECTORS, 1)
    with pytest.raises(RequestFailed, match="unknown input 'save'"):
        run.user("save", 100.3)
    run.user("finish", 100.3)
    assert run.action(100.3) == SendCommand("mag_calibration", {"action": "finish"})


def test_a_cancelled_calibration_puts_the_sensor_back_with_clear() -> None:
    run = start("mag_calibration")
    ok(run, {}, 100.0)
    ok(run, {}, 100.0)
    run.cancel(101.0)
    assert run.state is State.CANCELLED and not run.over
    assert run.action(101.0) == SendCommand("mag_calibration", {"action": "clear"})
    run.sending()
    run.answered(CommandResult("s", "mag_calibration", True, {}), 101.1)
    assert run.over and run.action(101.2) is None


def test_zero_looks_before_and_after_the_command() -> None:
    run = start("zero", {"type": "relative"}, Series.VG)
    run.observe(4, Reading(angles=Angles(3.0, -2.0, 10.0)), False, 100.0)
    assert run.angles["before"] == {"pitch": 3.0, "roll": -2.0, "yaw": 10.0}
    ok(run, {"result": "success"}, 100.1)  # set_zero_type; no heading asked: skipped
    run.observe(4, Reading(angles=Angles(0.0, 0.0, 10.0)), False, 100.2)  # not newer
    assert "after" not in run.angles
    run.observe(5, Reading(angles=Angles(0.01, 0.0, 10.0)), False, 100.3)
    assert run.state is State.DONE and run.angles["after"]["pitch"] == 0.01


def test_zero_on_a_mins_sets_the_relative_heading_too() -> None:
    run = start("zero", {"type": "absolute", "relative_heading": 90.0}, Series.MINS)
    run.observe(1, Reading(angles=Angles(0, 0, 0)), False, 100.0)
    assert run.action(100.0) == SendCommand("set_zero_type", {"type": "absolute"})
    ok(run, {}, 100.0)
    assert run.action(100.0) == SendCommand("set_relative_heading", {"degrees": 90.0})


@pytest.mark.parametrize(("name", "args", "series", "protocol", "kind", "message"), [
    ("spin", None, Series.AH, NATIVE, ErrorKind.NOT_FOUND, "unknown procedure 'spin' "
     "(known: gyro_calibration, mag_calibration, zero, change_address, change_baudrate)"),
    ("mag_calibration", None, Series.VG, NATIVE, ErrorKind.UNSUPPORTED,
     "VG sensors have no mag_calibration (it is for AH)"),
    ("mag_calibration", None, Series.AH, MODBUS, ErrorKind.UNSUPPORTED,
     "mag_calibration needs mag_calibration, which this AH sensor cannot carry"),
    ("zero", {"type": "relative", "relative_heading": 5.0}, Series.VG, NATIVE,
     ErrorKind.UNSUPPORTED, "zero needs set_relative_heading"),
    ("zero", {"type": "sideways"}, Series.VG, NATIVE, ErrorKind.BAD_ARGUMENTS,
     "zero: type: Input should be 'absolute' or 'relative'"),
    ("gyro_calibration", {"countdown_s": 600}, Series.VG, NATIVE, ErrorKind.BAD_ARGUMENTS,
     "countdown_s: Input should be less than or equal to 60"),
    ("gyro_calibration", [1], Series.VG, NATIVE, ErrorKind.BAD_ARGUMENTS,
     "arguments must be a JSON object"),
])
def test_what_cannot_run_is_refused_naming_why(name: str, args: Any, series: Series,
                                                protocol: WireProtocol, kind: ErrorKind,
                                                message: str) -> None:
    with pytest.raises(RequestFailed) as caught:
        validate(name, args, series, commands_for(series, protocol))
    assert caught.value.kind is kind and message in str(caught.value)


def test_every_procedure_uses_catalogue_commands_only() -> None:
    from imu_gateway.commands import CATALOGUE
    for spec in PROCEDURES.values():
        assert spec.commands <= set(CATALOGUE), spec.name


def test_what_each_sensor_can_run() -> None:
    changes = ["change_address", "change_baudrate"]
    assert available(Series.AH, commands_for(Series.AH, NATIVE)) == [
        "gyro_calibration", "mag_calibration", "zero", *changes]
    assert available(Series.AH, commands_for(Series.AH, MODBUS)) == [
        "gyro_calibration", "zero", *changes]
    assert available(Series.MINS, commands_for(Series.MINS, MODBUS)) == [
        "gyro_calibration", "zero", *changes]


def test_the_circle_ignores_readings_without_a_direction() -> None:
    trace = CircleTrace()
    trace.add(0.0, 0.0)
    trace.add(math.nan, 0.1)
    assert trace.coverage_percent == 0.0


def test_a_cancel_while_a_command_is_in_flight_still_clears_after_its_answer() -> None:
    """The answer to the command in flight when the cancel came is not the clear's:
    the clear is still sent after it (the sensor is not left half calibrated)."""
    run = start("mag_calibration")
    ok(run, {}, 100.0)  # clear
    action = run.action(100.1)
    assert action == SendCommand("mag_calibration", {"action": "start"})
    run.sending()  # start in flight
    run.cancel(100.2)
    assert run.action(100.2) == Wait(None)  # its answer first
    run.answered(CommandResult("s", "mag_calibration", True, {}), 100.3)
    assert not run.over
    assert run.action(100.3) == SendCommand("mag_calibration", {"action": "clear"})
    run.sending()
    run.answered(CommandResult("s", "mag_calibration", True, {}), 100.4)
    assert run.over and run.action(100.5) is None


# ------------------------------------------------------------ address and baud changes


def placed(protocol: WireProtocol = NATIVE, address: int = 0, baudrate: int = 9600,
           others: tuple[tuple[str, int], ...] = (), port: str = "/dev/ttyUSB0") -> Placement:
    return Placement("boom", "line", protocol, port, baudrate, address, others)


def change(name: str, args: dict[str, Any], where: Placement, now: float = 100.0) -> Run:
    spec, values = validate(name, args, Series.AH, commands_for(Series.AH, where.protocol),
                            where)
    return Run(spec, values, now, where)


def test_an_address_change_sends_then_changes_the_config_then_hears_the_sensor() -> None:
    run = change("change_address", {"address": 7}, placed())
    assert run.action(100.0) == SendCommand("set_address", {"address": 7})
    run.sending()
    with pytest.raises(RequestFailed) as caught:  # sent: no way back, no cancel
        run.cancel(100.1)
    assert caught.value.kind is ErrorKind.BUSY and "cannot be cancelled" in str(caught.value)
    run.answered(CommandResult("boom", "set_address", True, {"result": "success"}), 100.2)
    action = run.action(100.2)
    assert action == ChangeConfig(ConfigChange("line", "boom", "address", 7))
    run.sending()
    assert run.action(100.3) == Wait(None)  # the reload under way
    run.reconfigured({"applied": True, "saved": True}, None, 100.5)
    assert run.action(100.5) == Wait(110.5)  # a reading, within 10 s
    run.observe(1, Reading(angles=Angles(1.0, 2.0, 3.0)), False, 101.0)
    assert run.state is State.DONE and run.action(101.0) is None
    assert run.answers["config"] == {"applied": True, "saved": True}
    assert run.to_json(101.0)["offers"] == ["save"]


def test_an_address_change_is_cancelled_before_its_command_only() -> None:
    run = change("change_address", {"address": 7}, placed())
    run.cancel(100.0)
    assert run.state is State.CANCELLED and run.action(100.0) is None


@pytest.mark.parametrize(("name", "args", "where", "message"), [
    ("change_address", {"address": 3}, placed(others=(("arm", 3),)),
     "address 3 is taken on bus line by arm"),
    ("change_address", {"address": 0}, placed(), "boom is at address 0 already"),
    ("change_address", {"address": 0}, placed(MODBUS, address=1),
     "a modbus address is 1-247, not 0"),
    ("change_baudrate", {"baudrate": 19200}, placed(others=(("arm", 1), ("tip", 2))),
     "bus line has other sensors (arm, tip), which would stay at 9600 baud"),
    ("change_baudrate", {"baudrate": 9600}, placed(), "runs at 9600 baud already"),
    ("change_baudrate", {"baudrate": 12345}, placed(), "must be one of"),
])
def test_a_change_the_bus_cannot_take_is_refused_before_anything_is_sent(
        name: str, args: dict[str, Any], where: Placement, message: str) -> None:
    with pytest.raises(RequestFailed) as caught:
        change(name, args, where)
    assert caught.value.kind is ErrorKind.BAD_ARGUMENTS and message in str(caught.value)


def test_a_baud_change_on_a_serial_server_is_refused() -> None:
    with pytest.raises(RequestFailed) as caught:
        change("change_baudrate", {"baudrate": 19200}, placed(port="socket://10.0.0.9:4001"))
    assert caught.value.kind is ErrorKind.UNSUPPORTED
    assert "cannot change the serial server's rate" in str(caught.value)


def lost(run: Run, now: float) -> None:
    run.action(now)
    run.sending()
    run.answered(CommandResult("boom", run.spec.steps[0].command, False,  # type: ignore[union-attr]
                               error="boom: it was sent but not confirmed (timeout)",
                               kind=ErrorKind.UNCONFIRMED), now)


def test_a_lost_answer_is_read_back_and_never_sent_again() -> None:
    run = change("change_address", {"address": 7}, placed())
    lost(run, 100.0)
    assert run.action(100.0) == SendCommand("read_settings", {})  # not set_address again
    ok(run, {"zero_type": "absolute"}, 100.5)
    assert run.state is State.FAILED and run.kind is ErrorKind.UNCONFIRMED
    assert "read back, boom still answers at address 0: it was not changed, nor was the " \
           "config" in (run.error or "")


def test_a_lost_answer_and_no_read_back_says_where_the_sensor_may_be() -> None:
    run = change("change_address", {"address": 7}, placed())
    lost(run, 100.0)
    run.action(100.0)
    run.sending()
    run.answered(CommandResult("boom", "read_settings", False, error="timeout",
                               kind=ErrorKind.TIMEOUT), 101.0)
    assert run.state is State.FAILED
    assert "boom may be at address 7 now, or still at address 0" in (run.error or "")
    assert "scan" in (run.error or "")


def test_a_modbus_baud_change_read_back_at_the_new_rate_took() -> None:
    """Modbus: the line switched before the verifying read; a read back answered there
    proves the sensor is at the new rate: on to the config."""
    run = change("change_baudrate", {"baudrate": 19200}, placed(MODBUS, address=1))
    lost(run, 100.0)
    ok(run, {"zero_type": "absolute", "product_address": 1}, 100.5)
    assert run.action(100.5) == ChangeConfig(ConfigChange("line", None, "baudrate", 19200))


def test_a_config_that_cannot_follow_says_what_state_the_sensor_is_in() -> None:
    run = change("change_baudrate", {"baudrate": 19200}, placed())
    ok(run, {"result": "success"}, 100.0)
    run.action(100.0)
    run.sending()
    run.reconfigured(None, "the new config was refused: buses[0].baudrate: …", 100.5)
    assert run.state is State.FAILED
    assert run.error == (
        "boom and bus line now run at 19200 baud (verified), and the gateway follows until "
        "it restarts; but the config could not follow: the new config was refused: "
        "buses[0].baudrate: …. Put `baudrate: 19200` on bus line in the config (the Setup "
        "page, or PUT /api/v1/config), and send save to the sensor; else after a restart "
        "the gateway opens the line at 9600 baud and does not hear it")


def test_the_config_change_keeps_the_rest_of_the_config() -> None:
    data = {"gateway_id": "g", "buses": [
        {"name": "other", "baudrate": 9600, "sensors": [{"name": "boom", "address": 0}]},
        {"name": "line", "baudrate": 9600, "sensors": [{"name": "arm"}, {"name": "boom"}]}]}
    ConfigChange("line", "boom", "address", 9).applied_to(data)
    ConfigChange("line", None, "baudrate", 19200).applied_to(data)
    assert data["buses"] == [
        {"name": "other", "baudrate": 9600, "sensors": [{"name": "boom", "address": 0}]},
        {"name": "line", "baudrate": 19200, "sensors": [{"name": "arm"},
                                                        {"name": "boom", "address": 9}]}]
    with pytest.raises(ValueError, match="bus line has no sensor 'tip' now"):
        ConfigChange("line", "tip", "address", 9).applied_to(data)
