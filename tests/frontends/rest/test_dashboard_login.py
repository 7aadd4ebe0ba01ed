"""Logging in to the dashboard (docs/dashboard.md, "Logging in") in a real headless
Chromium, against ``python -m imu_gateway run`` on a simulated sensor whose alarm is
active, with users of two roles (``http.users``).

A viewer logs in with the form: no command, acknowledge or capture button, and a POST
sent from her page anyway is refused 403 (nothing changes, seen through REST).  An
operator logs in, acknowledges with the button, and the journal names him; the
credential is in ``sessionStorage``, in no URL the page requested; he logs out, and
the session's token is refused from then on.  Waits are deadlines on a condition."""

from __future__ import annotations

import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from test_dashboard import FAST, bus, chromium, console_errors, gateway, get_json, log_in, wait

from imu_gateway.model import Series, WireProtocol
from imu_gateway.passwords import hash_password
from imu_gateway.simulator import make_sensor, simulated

PASSWORDS = {"vera": "vera sees", "otto": "otto acts"}
ALARM = {"name": "boom_lean", "field": "tilt", "above": 5.0, "severity": "warning"}

#: What the page offers: its buttons, and the alarm's state as it shows it.
OFFERS_JS = """
const card = document.querySelector('[data-sensor="boom"]');
const line = card && card.querySelector('li[data-alarm="boom_lean"]');
if (!line) return null;
return {commands: card.querySelectorAll(".commands button").length,
        ack: Boolean(line.querySelector("button.ack")), state: line.dataset.state,
        take: !document.getElementById("capture-take").hidden,
        who: document.getElementById("who").textContent,
        stored: sessionStorage.getItem("imu-gateway.credential"),
        urls: performance.getEntriesByType("resource").map((e) => e.name)};
"""
#: A POST from the page with its credential (``arguments[0]``: the path).
POST_JS = """
const done = arguments[arguments.length - 1];
fetch(arguments[0], {method: "POST", headers: window.imuAuth.headers()})
  .then(async (r) => done([r.status, await r.json()]), (e) => done([0, String(e)]));
"""


def offers(driver: Any, ok: Any, what: str) -> dict[str, Any]:
    def check() -> dict[str, Any] | None:
        value = driver.execute_script(OFFERS_JS)
        return value if value is not None and ok(value) else None

    return wait(check, what)


def status_with(url: str, token: str) -> int:
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return int(response.status)
    except urllib.error.HTTPError as error:
        return int(error.code)


@pytest.fixture
def leaning() -> Any:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([boom]) as line:
        line.call(boom.lean, 9.0, 0.0).result(5)
        yield line


def test_a_viewer_gets_no_buttons_and_403_an_operator_acknowledges_and_logs_out(
        tmp_path: Path, leaning: Any) -> None:
    users = {name: {"role": role, "password": hash_password(PASSWORDS[name])}
             for name, role in (("vera", "viewer"), ("otto", "operator"))}
    cfg = {"gateway_id": "dash", "http": {"users": users, "allow_commands": True},
           "capture": {"dir": str(tmp_path / "captures"), "pre_s": 1.0, "post_s": 1.0},
           "buses": [bus("a", leaning.path, "native", [
               {"name": "boom", "series": "AH", "poll_hz": 20, "alarms": [ALARM]}])]}
    with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
        # The viewer: logged in, and nothing to press.
        log_in(driver, base, "vera", PASSWORDS["vera"], "viewer")
        vera = offers(driver, lambda o: o["state"] == "active_unacked", "the alarm shown")
        assert vera["who"] == "vera · viewer"
        assert (vera["commands"], vera["ack"], vera["take"]) == (0, False, False)
        # Her page sends the POST anyway: refused for her role, and nothing changed.
        status, body = driver.execute_async_script(POST_JS, "api/v1/alarms/boom/boom_lean/ack")
        assert (status, body["kind"]) == (403, "forbidden")
        assert "vera has the role viewer; this needs operator" in body["error"]
        status, body = driver.execute_async_script(POST_JS, "api/v1/captures")
        assert status == 403
        assert [a["state"] for a in get_json(f"{base}/api/v1/alarms")
                if a["alarm"] == "boom_lean"] == ["active_unacked"]
        assert get_json(f"{base}/api/v1/captures") == []
        console_errors(driver)  # (the browser logs the 403s)
        driver.find_element("id", "logout").click()
        wait(lambda: driver.execute_script(
            "return document.getElementById('login-open') && "
            "!document.getElementById('login-open').hidden"), "logged out")

        # The operator: the buttons; acknowledges; the journal says who.
        log_in(driver, base, "otto", PASSWORDS["otto"], "operator")
        otto = offers(driver, lambda o: o["ack"] and o["commands"] > 0, "the operator's buttons")
        assert otto["take"] and otto["who"] == "otto · operator"
        token = otto["stored"]
        assert token and not [u for u in otto["urls"] if token in u]
        driver.find_element("css selector", 'li[data-alarm="boom_lean"] button.ack').click()
        offers(driver, lambda o: o["state"] == "active_acked", "acknowledged")
        journal = get_json(f"{base}/api/v1/alarms/journal")
        assert journal[-1]["to"] == "active_acked"
        assert journal[-1]["by"] == "dashboard (rest 127.0.0.1, otto)"
        assert status_with(f"{base}/api/v1/me", token) == 200

        # Log out: the form's button again, and the session's token is dead.
        driver.find_element("id", "logout").click()
        wait(lambda: driver.execute_script(
            "return sessionStorage.getItem('imu-gateway.credential') === null && "
            "!document.getElementById('login-open').hidden"), "logged out")
        assert status_with(f"{base}/api/v1/me", token) == 401
        offers(driver, lambda o: not o["ack"] and o["commands"] == 0 and not o["take"],
               "a viewer's page again")
        assert console_errors(driver) == []
