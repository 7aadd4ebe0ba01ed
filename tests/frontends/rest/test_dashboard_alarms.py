"""Alarms on the live dashboard (docs/dashboard.md, docs/alarms.md) in a real headless
Chromium, against ``python -m imu_gateway run`` on simulated sensors.

A simulated sensor leans past its tilt limit (``SimSensor.lean``), and the page shows
the alarm (the banner's count by severity, the card's badge, the alarm's line) no
sooner than its on-delay; a viewer (not logged in) has no acknowledge button; the
operator, logged in with the form, acknowledges; the value comes back inside the limit
but not through the hysteresis, and the alarm stays; then through it, and it clears.
The journal list and the marks on the trend chart follow.  A sensor that stops
answering raises its critical communication alarm.  Waits are deadlines on a condition."""

from __future__ import annotations

import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from test_dashboard import (
    ARTIFACTS,
    FAST,
    bus,
    chromium,
    console_errors,
    gateway,
    get_json,
    log_in,
    screenshot,
    wait,
)

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, make_sensor, simulated

TOKEN = "dash-alarm-token"
ON_DELAY = 1.0
LEAN_ALARM = {"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
              "on_delay_s": ON_DELAY, "severity": "warning"}

# What the page shows of the alarms, with ``arguments[0]``'s card, in one round trip.
ALARMS_JS = """
const banner = document.getElementById("alarm-banner");
const card = document.querySelector(`[data-sensor="${arguments[0]}"]`);
if (!card || !banner) return null;
const lines = {};
for (const li of card.querySelectorAll("ul.alarms li"))
  lines[li.dataset.alarm] = {state: li.dataset.state, text: li.textContent,
                             ack: Boolean(li.querySelector("button.ack"))};
const badge = card.querySelector('[data-field="alarm_badge"]');
const marks = {};
for (const c of card.querySelectorAll("canvas.trend"))
  marks[c.dataset.group] = Number(c.dataset.marks || 0);
const tilt = card.querySelector('[data-field="tilt"]');
return {banner: banner.hidden ? null : {text: banner.textContent, ...banner.dataset},
        badge: badge.hidden ? null : badge.textContent, lines, marks,
        result: card.querySelector(".alarm-result").textContent,
        tilt: tilt ? tilt.textContent : null,
        journal: [...document.querySelectorAll("#journal li")].map((li) => (
          {alarm: li.dataset.alarm, from: li.dataset.from, to: li.dataset.to,
           text: li.textContent}))};
"""


def page(driver: Any, sensor: str) -> dict[str, Any] | None:
    value = driver.execute_script(ALARMS_JS, sensor)
    assert value is None or isinstance(value, dict)
    return value


def page_when(driver: Any, sensor: str, ok: Callable[[dict[str, Any]], bool],
              what: str) -> dict[str, Any]:
    def check() -> dict[str, Any] | None:
        p = page(driver, sensor)
        return p if p is not None and p["banner"] is not None and ok(p) else None

    return wait(check, what)


def alarm_state(base: str, sensor: str, alarm: str) -> dict[str, Any]:
    states = get_json(f"{base}/api/v1/alarms")
    found = next(a for a in states if (a["sensor"], a["alarm"]) == (sensor, alarm))
    assert isinstance(found, dict)
    return found


def click_ack(driver: Any, sensor: str, alarm: str) -> None:
    driver.find_element("css selector", f'[data-sensor="{sensor}"] li[data-alarm="{alarm}"] '
                        "button.ack").click()


def test_a_lean_raises_the_alarm_on_the_page_and_only_the_operator_acknowledges(
        tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    mast_faults = Faults()
    mast = make_sensor(WireProtocol.NATIVE, Series.VG, 0, baud=FAST, faults=mast_faults)
    # (each on a line of its own: a mast that stops answering does not slow the boom)
    with simulated([boom]) as line, simulated([mast]) as mast_line:
        line.call(boom.lean, 1.0, 0.0).result(5)
        cfg = {"gateway_id": "dash", "http": {"token": TOKEN}, "buses": [
            bus("a", line.path, "native", [
                {"name": "boom", "series": "AH", "poll_hz": 20, "alarms": [LEAN_ALARM]}]),
            bus("b", mast_line.path, "native", [
                {"name": "mast", "series": "VG", "poll_hz": 10, "stale_after_ms": 1500}])]}
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            # A viewer, not logged in.
            driver.get(base + "/")
            calm = page_when(driver, "boom", lambda p: p["tilt"] == "1.00", "boom at 1°")
            assert calm["banner"]["text"] == "no active alarm"
            assert calm["badge"] is None and calm["lines"] == {} and calm["journal"] == []

            leaned_at = time.time()
            line.call(boom.lean, 7.5, 0.0).result(5)
            raised = page_when(driver, "boom", lambda p: p["banner"]["warning"] == "1",
                               "the banner counts the warning")
            seen_at = time.time()
            # not before the lean had held for the on-delay, on the page as in REST
            assert seen_at >= leaned_at + ON_DELAY
            rest = alarm_state(base, "boom", "boom_lean")
            assert rest["state"] == "active_unacked" and rest["value"] == 7.5
            # (to the millisecond of the time stamps)
            assert datetime.fromisoformat(rest["since"]).timestamp() >= \
                leaned_at + ON_DELAY - 0.002
            assert raised["banner"]["text"] == \
                "active alarms: 0 critical · 1 warning · 0 info · 1 to acknowledge"
            assert raised["badge"] == "1 alarm · warning"  # in words, not colour alone
            lean = raised["lines"]["boom_lean"]
            assert lean["state"] == "active_unacked" and not lean["ack"]  # a viewer's page
            assert "warning · active, unacknowledged · tilt 7.50 (limit 5.00)" in lean["text"]
            assert len(get_json(f"{base}/api/v1/alarms/journal")) == 1

            # The operator (the admin's token: an admin may all an operator may), logged
            # in with the form: the state and the journal load with the page.
            log_in(driver, base, "", TOKEN, "admin")
            page_when(driver, "boom", lambda p: "boom_lean" in p["lines"], "the alarm's line")
            click_ack(driver, "boom", "boom_lean")
            acked = page_when(driver, "boom",
                              lambda p: p["lines"]["boom_lean"]["state"] == "active_acked",
                              "the alarm acknowledged")
            assert acked["result"] == "boom_lean: acknowledged"
            assert not acked["lines"]["boom_lean"]["ack"]
            assert acked["banner"]["warning"] == "1" and acked["banner"]["unacked"] == "0"
            assert alarm_state(base, "boom", "boom_lean")["state"] == "active_acked"
            journal = page_when(driver, "boom", lambda p: len(p["journal"]) == 2,
                                "two transitions listed")["journal"]
            assert [(j["alarm"], j["from"], j["to"]) for j in journal] == [
                ("boom/boom_lean", "active_unacked", "active_acked"),  # newest first
                ("boom/boom_lean", "normal", "active_unacked")]
            assert journal[0]["text"].endswith("by dashboard (rest 127.0.0.1, http.token)")
            assert "normal → active, unacknowledged · tilt 7.50 (limit 5.00)" in \
                journal[1]["text"]
            marked = page_when(driver, "boom", lambda p: p["marks"].get("tilt") == 2,
                               "both transitions marked on the tilt trend")
            assert marked["marks"]["angles"] == 0  # (an alarm on tilt: its chart only)
            ARTIFACTS.mkdir(exist_ok=True)
            assert driver.find_element(
                "css selector", '[data-sensor="boom"] canvas.trend[data-group="tilt"]'
            ).screenshot(str(ARTIFACTS / "dashboard-alarm-trend.png"))

            # Back inside the limit, not through the hysteresis (4.7 > 4.5): still active.
            line.call(boom.lean, 4.7, 0.0).result(5)
            page_when(driver, "boom", lambda p: p["tilt"] == "4.70", "boom at 4.7°")
            seq = get_json(f"{base}/api/v1/sensors/boom")["seq"]
            wait(lambda: get_json(f"{base}/api/v1/sensors/boom")["seq"] >= seq + 10,
                 "ten more samples evaluated")
            held = page(driver, "boom")
            assert held is not None and held["banner"]["warning"] == "1"
            assert held["lines"]["boom_lean"]["state"] == "active_acked"
            assert alarm_state(base, "boom", "boom_lean")["state"] == "active_acked"
            # Through it: cleared, the badge gone, the journal says so.
            line.call(boom.lean, 4.0, 0.0).result(5)
            cleared = page_when(driver, "boom", lambda p: p["banner"]["warning"] == "0",
                                "the alarm cleared")
            assert cleared["badge"] is None and cleared["lines"] == {}
            assert cleared["banner"]["text"] == "no active alarm"
            back = page_when(driver, "boom", lambda p: len(p["journal"]) == 3,
                             "the clearing listed")["journal"][0]
            assert (back["from"], back["to"]) == ("active_acked", "normal")
            assert "tilt 4.00 (limit 5.00)" in back["text"]

            # A sensor that stops answering: its critical communication alarm.
            mast_faults.stalled = True
            mute = page_when(driver, "mast", lambda p: p["banner"]["critical"] == "1",
                             "the communication alarm counted")
            assert mute["badge"] == "1 alarm · critical"
            assert mute["lines"]["communication"]["state"] == "active_unacked"
            assert mute["banner"]["text"].startswith("active alarms: 1 critical · 0 warning")
            # the communication alarm, of no one field: marked on every chart of the mast
            page_when(driver, "mast", lambda p: bool(p["marks"]) and
                      all(n == 1 for n in p["marks"].values()),
                      "the communication alarm marked on each of the mast's charts")
            screenshot(driver, tmp_path, "dashboard-alarms.png")
            assert console_errors(driver) == []


def test_without_credentials_set_nobody_may_acknowledge(tmp_path: Path) -> None:
    """A gateway with no ``http.users``, ``http.tokens`` or ``http.token``: the page has
    no acknowledge button, and a POST from the page anyway is refused (forbidden),
    naming the settings that allow it; the alarm stays as it was."""
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([boom]) as line:
        line.call(boom.lean, 20.0, 0.0).result(5)
        cfg = {"gateway_id": "dash", "buses": [bus("a", line.path, "native", [
            {"name": "boom", "series": "AH", "poll_hz": 20,
             "alarms": [{**LEAN_ALARM, "on_delay_s": 0, "severity": "critical"}]}])]}
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            driver.get(f"{base}/?token=anything")
            raised = page_when(driver, "boom", lambda p: "boom_lean" in p["lines"],
                               "the alarm's line")
            assert raised["banner"]["critical"] == "1" and raised["badge"] == "1 alarm · critical"
            assert not raised["lines"]["boom_lean"]["ack"]
            status, body = driver.execute_async_script(POST_JS, "api/v1/alarms/boom/boom_lean/ack")
            assert status == 403 and body["kind"] == "forbidden"
            assert "http.users, http.tokens or http.token" in body["error"]
            assert alarm_state(base, "boom", "boom_lean")["state"] == "active_unacked"


#: A POST from the page (``arguments[0]``), as a script of a viewer's would send it.
POST_JS = """
const done = arguments[arguments.length - 1];
fetch(arguments[0], {method: "POST", headers: window.imuAuth.headers()})
  .then(async (r) => done([r.status, await r.json()]), (e) => done([0, String(e)]));
"""
