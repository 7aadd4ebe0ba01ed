"""Reload without a restart (docs/configuration.md, "Changing the config while
running"): the diff on values alone, then a reload under load against simulated lines."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO, Any

import httpx
import pytest
from pymodbus.client import AsyncModbusTcpClient
from support.harness import free_port, running, until

from imu_gateway.config import config_from_dict
from imu_gateway.model import Series, WireProtocol
from imu_gateway.reload import diff_configs
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
READING = Motion.from_seed(3).sample(10.0)


def bus(name: str, port: str, sensors: list[dict[str, Any]], **more: Any) -> dict[str, Any]:
    return {"name": name, "port": port, "protocol": "native", "baudrate": FAST,
            "timeout_ms": 300, "sensors": sensors, **more}


def gateway(buses: list[dict[str, Any]], **sections: Any) -> dict[str, Any]:
    return {"gateway_id": "test", "buses": buses, **sections}


def test_an_unchanged_config_is_no_change() -> None:
    config = config_from_dict(gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])]))
    diff = diff_configs(config, config)
    assert diff.empty and diff.summary() == "reload: no change"


def test_the_diff_names_each_part_and_its_change() -> None:
    """A sensor added changes its bus's schedule only; a baud rate changed restarts that
    bus; a bus and a front end untouched are named unchanged; http is applied live."""
    old = config_from_dict(gateway(
        [bus("line-a", "/dev/null", [{"name": "boom", "series": "AH"}]),
         bus("line-b", "/dev/zero", [{"name": "arm", "series": "VG"}], baudrate=9600),
         bus("line-c", "/dev/tty", [{"name": "mast", "series": "IMU"}])],
        modbus={"listen": "127.0.0.1:0"}, http={"listen": "127.0.0.1:8080"}), env={})
    new = config_from_dict(gateway(
        [bus("line-a", "/dev/null", [{"name": "boom", "series": "AH"},
                                     {"name": "boom2", "series": "AH", "address": 1}]),
         bus("line-b", "/dev/zero", [{"name": "arm", "series": "VG"}], baudrate=19200),
         bus("line-c", "/dev/tty", [{"name": "mast", "series": "IMU"}])],
        modbus={"listen": "127.0.0.1:0"}, http={"listen": "127.0.0.1:8081"}), env={})
    diff = diff_configs(old, new)
    assert [(m.sensor, m.bus) for m in diff.sensors_added] == [("boom2", "line-a")]
    assert diff.buses_restarted == ("line-b",) and diff.buses_rescheduled == ("line-a",)
    assert diff.buses_unchanged == ("line-c",)
    assert [c.describe() for c in diff.buses_changed] == ["line-b (baudrate 9600→19200)"]
    assert diff.frontends_unchanged == ("modbus",)
    assert [c.name for c in diff.sections_changed] == ["http"] and not diff.needs_restart
    assert diff.summary() == (
        "reload: +1 sensor (boom2 on line-a, its schedule only), line-b restarted "
        "(baudrate 9600→19200), sensor arm (unit_id 2→3), sensor mast (unit_id 3→4), "
        "http applied (listen 127.0.0.1:8080→127.0.0.1:8081), "
        "unchanged: line-c, modbus")


def test_a_top_level_value_changed_is_named_once() -> None:
    """``hand_over_ms`` (a number at the top): applied live, shown ``name (0→20)``."""
    old = config_from_dict(gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])]))
    new = config_from_dict({**gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])]),
                            "hand_over_ms": 20})
    diff = diff_configs(old, new)
    assert [c.describe() for c in diff.sections_changed] == ["hand_over_ms (0→20)"]
    assert not diff.needs_restart and not diff.buses_changed


def test_a_kept_sensor_s_bus_setting_changed_restarts_its_bus() -> None:
    """A sensor removed beside a kept one whose rate changed: the bus restarts (the
    summary says so), it is not merely rescheduled."""
    old = config_from_dict(gateway([bus("a", "/dev/null", [
        {"name": "s", "series": "AH"}, {"name": "t", "series": "AH", "address": 1}])]))
    new = config_from_dict(gateway([bus("a", "/dev/null", [
        {"name": "s", "series": "AH", "poll_hz": 5}])]))
    diff = diff_configs(old, new)
    assert diff.buses_restarted == ("a",) and diff.buses_rescheduled == ()
    assert diff.summary().startswith("reload: -1 sensor (t on a, a restarted), a restarted")
    assert diff.to_json()["buses"]["rescheduled"] == []


def test_unit_ids_and_alarms_restart_no_bus() -> None:
    """A unit id or an alarm is not the bus's business: the bus is kept."""
    old = config_from_dict(gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])]))
    new = config_from_dict(gateway([bus("a", "/dev/null", [
        {"name": "s", "series": "AH", "unit_id": 9,
         "alarms": [{"name": "tilt", "field": "pitch", "above": 5}]}])]))
    diff = diff_configs(old, new)
    assert diff.buses_restarted == () and diff.buses_changed == ()
    assert [c.name for c in diff.sensors_changed] == ["s"] and diff.sensor_set_changed


def test_a_secret_changed_is_named_never_shown() -> None:
    old = config_from_dict(gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])],
                                   http={"token": "old-secret"}))
    new = config_from_dict(gateway([bus("a", "/dev/null", [{"name": "s", "series": "AH"}])],
                                   http={"token": "new-secret"}))
    summary = diff_configs(old, new).summary()
    assert "token changed" in summary and "secret" not in summary


async def _poll_modbus(port: int, gaps: list[float], stop: asyncio.Event) -> None:
    async with AsyncModbusTcpClient("127.0.0.1", port=port) as client:
        last = asyncio.get_running_loop().time()
        while not stop.is_set():
            answer = await client.read_input_registers(0, count=4, device_id=1)
            assert not answer.isError(), answer
            now = asyncio.get_running_loop().time()
            gaps.append(now - last)
            last = now
            await asyncio.sleep(0.02)


@pytest.mark.anyio
async def test_a_reload_under_load_keeps_the_unchanged_bus_running() -> None:
    """Line a unchanged, line b changed (a sensor added): a Modbus TCP poller of a's
    sensor sees no gap longer than its normal period, a's master and port are the same
    (opened once), its counters go on; b's sensor is added and answers."""
    a = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))
    b1 = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))
    b2 = make_sensor(WireProtocol.NATIVE, Series.AH, address=1, baud=FAST,
                     source=hold(READING))
    with simulated([a]) as line_a, simulated([b1, b2]) as line_b:
        buses = [bus("a", line_a.path, [{"name": "boom", "series": "AH", "unit_id": 1}]),
                 bus("b", line_b.path, [{"name": "arm", "series": "AH", "unit_id": 2}])]
        first = gateway(buses, modbus={"listen": "127.0.0.1:0"})
        async with running(first) as gw:
            assert gw.modbus is not None
            await until(lambda: gw.cache.snapshot("boom").has_reading
                        and gw.cache.snapshot("arm").has_reading)
            master_a = gw.masters["a"]
            before = next(s.transactions for s in gw.stats() if s.name == "a")
            gaps: list[float] = []
            stop = asyncio.Event()
            poller = asyncio.create_task(_poll_modbus(gw.modbus.port, gaps, stop))
            await until(lambda: len(gaps) > 20)
            normal = max(gaps[1:])
            buses[1]["sensors"].append({"name": "arm2", "series": "AH", "address": 1,
                                         "unit_id": 3})
            diff = await gw.reloader._apply(config_from_dict(first, env={}))
            assert diff.buses_rescheduled == ("b",) and diff.buses_unchanged == ("a",)
            count = len(gaps)
            await until(lambda: len(gaps) > count + 20)
            stop.set()
            await poller
            after = gaps[count - 1:]
            assert max(after) <= max(2 * normal, 0.25), (max(after), normal)
            assert gw.masters["a"] is master_a
            assert master_a.link._opens == 1  # the port was opened once, never again
            # its counters go on from where they were (not from zero)
            assert next(s.transactions for s in gw.stats() if s.name == "a") > before
            await until(lambda: gw.cache.snapshot("arm2").has_reading)
            assert 3 in gw.modbus.units


def test_sighup_reads_the_file_again_and_a_broken_one_changes_nothing(tmp_path: Path) -> None:
    """``imu-gateway run`` as a process: SIGHUP with a broken file logs its problems and
    keeps the running config; SIGHUP with a sensor added logs the reload's summary, and
    the new sensor reads (REST), while the first one goes on."""
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200),
               make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=115200)]
    port = free_port()
    with simulated(sensors) as sim:
        config = tmp_path / "gateway.yaml"
        good = SIGHUP_CONFIG.format(port=sim.path, http=port)
        config.write_text(good)
        with subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(config)],
                              stderr=subprocess.PIPE, text=True) as proc:
            watchdog = threading.Timer(90, proc.kill)
            watchdog.start()
            assert proc.stderr is not None
            try:
                wait_for_line(proc.stderr, "sensor boom: online")
                config.write_text(good.replace("baudrate: 115200", "baudrate: 115201"))
                proc.send_signal(signal.SIGHUP)
                refused = wait_for_line(proc.stderr, "reload refused, nothing changed")
                assert "buses[0].baudrate" in refused, refused
                config.write_text(good + "      - {name: boom2, series: AH, address: 1, "
                                  "poll_hz: 10}\n")
                proc.send_signal(signal.SIGHUP)
                summary = wait_for_line(proc.stderr, "reload:")
                assert "boom2" in summary, summary
                wait_for_line(proc.stderr, "sensor boom2: online")
                with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
                    names = [s["name"] for s in http.get("/api/v1/sensors").json()]
                    assert names == ["boom", "boom2"], names
                    assert http.get("/api/v1/sensors/boom/reading").status_code == 200
                proc.send_signal(signal.SIGTERM)
                assert proc.wait(timeout=20) == 0
            finally:
                watchdog.cancel()


SIGHUP_CONFIG = """gateway_id: hup
http: {{listen: "127.0.0.1:{http}"}}
buses:
  - name: line-a
    port: {port}
    baudrate: 115200
    protocol: native
    sensors:
      - {{name: boom, series: AH, address: 0, poll_hz: 10}}
"""


def wait_for_line(stream: IO[str], text: str) -> str:
    """The first line of ``stream`` with ``text`` in it (the watchdog ends a process
    that never writes it)."""
    for line in stream:
        if text in line:
            return line
    raise AssertionError(f"the gateway ended without logging {text!r}")
