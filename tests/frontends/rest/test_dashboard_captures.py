"""Captures on the live dashboard (docs/dashboard.md, docs/alarms.md "Captures") in a real
headless Chromium, against ``python -m imu_gateway run`` on simulated sensors.

A simulated sensor leans past an alarm that ``capture.on_alarms`` names: the capture it
triggers appears in the page's list (time, trigger, size as REST lists them), no sooner
than ``post_s`` after the trigger, and its link's ``href`` downloads the ZIP (httpx, then
``zipfile``).  A viewer (not logged in) has no "Take a capture" button; the operator,
logged in with the form, takes one and sees it listed.  With a read token the link is
clicked in the browser and the ZIP lands in its download folder.  A gateway without a
``capture:`` section shows a note, no list and no button, and the page logs no error.
Waits are deadlines on a condition."""

from __future__ import annotations

import io
import json
import time
import zipfile
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
from selenium.common.exceptions import (
    ElementClickInterceptedException,
    StaleElementReferenceException,
)
from test_dashboard import (
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
from imu_gateway.simulator import make_sensor, simulated

TOKEN = "dash-capture-token"
POST_S = 1.0
LEAN_ALARM = {"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
              "severity": "warning"}

# What the page shows of the captures, in one round trip.
CAPTURES_JS = """
const section = document.getElementById("captures-section");
if (!section || section.hidden) return null;
const result = document.getElementById("capture-result");
return {mode: section.dataset.capture,
        note: document.getElementById("captures-off").hidden ? null
          : document.getElementById("captures-off").textContent.replace(/\\s+/g, " ").trim(),
        listed: !document.getElementById("captures-on").hidden,
        button: !document.getElementById("capture-take").hidden
          && !document.getElementById("captures-on").hidden,
        result: {text: result.textContent, ok: result.dataset.ok || null,
                 capture: result.dataset.capture || null},
        captures: [...document.querySelectorAll("#captures li")].map((li) => ({
          id: li.dataset.capture, trigger: li.dataset.trigger, alarm: li.dataset.alarm || null,
          time: li.dataset.time, size: Number(li.dataset.size), text: li.textContent,
          href: li.querySelector("a.download").href,
          file: li.querySelector("a.download").getAttribute("download")}))};
"""


def page(driver: Any) -> dict[str, Any] | None:
    value = driver.execute_script(CAPTURES_JS)
    assert value is None or isinstance(value, dict)
    return value


def page_when(driver: Any, ok: Callable[[dict[str, Any]], bool], what: str,
              timeout: float = 15.0) -> dict[str, Any]:
    """The page's state once ``ok``; past ``timeout``, the failure shows the last one
    seen (the button's result says why a capture was not taken)."""
    last: list[dict[str, Any] | None] = [None]

    def check() -> dict[str, Any] | None:
        p = last[0] = page(driver)
        return p if p is not None and ok(p) else None

    try:
        return wait(check, what, timeout)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; the page last showed {last[0]}") from None


def click_until_handled(driver: Any, css: str, what: str,
                        handled: Callable[[dict[str, Any]], bool]) -> None:
    """Click the element at ``css`` until the page's handler ran: its first act, before
    any request, shows on the page (``handled`` knows where).  Beside CPU burners a
    click once landed while the page was still moving and reached nothing; a click the
    handler never saw sent nothing, so clicking again cannot take a second capture."""
    def ran() -> bool:
        p = page(driver)
        return p is not None and handled(p)

    for _ in range(5):
        try:
            driver.find_element("css selector", css).click()
        except (ElementClickInterceptedException, StaleElementReferenceException):
            continue  # (the page moved under the click: it reached nothing)
        try:
            wait(ran, f"{what}'s handler", timeout=3.0)
            return
        except AssertionError:
            continue
    raise AssertionError(f"five clicks on {what} never reached its handler; the page "
                         f"last showed {page(driver)}")


def take_capture(driver: Any) -> None:
    """(The result is empty until the button is used: its handler writes "taking a
    capture…" first.)"""
    click_until_handled(driver, "#capture-take", "'Take a capture'",
                        lambda p: bool(p["result"]["text"]))


def download(driver: Any, folder: Path) -> None:
    """The first capture's link: its handler says "downloading…" on it first; a
    fast download may be over before the page is looked at (a file in ``folder``), a
    failed one says so in the result."""
    click_until_handled(driver, "#captures li a.download", "the download link",
                        lambda p: any("downloading…" in c["text"] for c in p["captures"])
                        or p["result"]["text"].startswith("download:")
                        or any(folder.iterdir()))


def config(line: str, folder: Path, http: dict[str, Any], **capture: Any) -> dict[str, Any]:
    return {"gateway_id": "dash", "http": http, "buses": [bus("a", line, "native", [
        {"name": "boom", "series": "AH", "poll_hz": 20, "alarms": [LEAN_ALARM]}])],
        "capture": {"dir": str(folder), "pre_s": 1.0, "post_s": POST_S, **capture}}


def opened(content: bytes) -> zipfile.ZipFile:
    archive = zipfile.ZipFile(io.BytesIO(content))
    assert archive.testzip() is None
    return archive


def test_a_capture_on_an_alarm_is_listed_and_the_button_is_the_operators(
        tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([boom]) as line:
        line.call(boom.lean, 1.0, 0.0).result(5)
        cfg = config(line.path, tmp_path / "captures",
                     {"token": TOKEN, "allow_commands": True}, on_alarms=["boom_lean"])
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            # A viewer, not logged in: the list, empty, and no button.
            driver.get(base + "/")
            empty = page_when(driver, lambda p: p["mode"] == "on", "the captures' section")
            assert empty["listed"] and not empty["button"] and empty["note"] is None
            assert empty["captures"] == []

            line.call(boom.lean, 7.5, 0.0).result(5)
            shown = page_when(driver, lambda p: len(p["captures"]) == 1,
                              "the alarm's capture listed")
            seen_at = time.time()
            rest = get_json(f"{base}/api/v1/captures")
            assert len(rest) == 1
            entry = shown["captures"][0]
            assert {k: entry[k] for k in ("id", "trigger", "alarm", "time", "size")} == rest[0]
            assert (entry["trigger"], entry["alarm"]) == ("alarm", "boom/boom_lean")
            assert "alarm boom/boom_lean · " in entry["text"] and "KiB · download" in entry["text"]
            # written post_s after its trigger, and not listed before
            triggered = datetime.fromisoformat(entry["time"]).timestamp()
            assert seen_at >= triggered + POST_S
            print(f"listed {seen_at - triggered:.2f} s after the trigger (post_s {POST_S})")

            # The link, as the page has it, downloads the ZIP.
            assert entry["href"] == f"{base}/api/v1/captures/{entry['id']}"
            assert entry["file"] == f"imu-gateway-capture-{entry['id']}.zip"
            response = httpx.get(entry["href"], timeout=10)
            assert response.status_code == 200
            assert response.headers["content-type"] == "application/zip"
            archive = opened(response.content)
            assert {"boom.csv", "frames.jsonl", "meta.json"} <= set(archive.namelist())
            meta = json.loads(archive.read("meta.json"))
            assert meta["id"] == entry["id"] and meta["trigger"]["alarm"] == "boom/boom_lean"
            assert len(response.content) == entry["size"]

            # The operator (the admin's token, logged in with the form): the button; a
            # capture taken, and listed once written.
            log_in(driver, base, "", TOKEN, "admin")
            page_when(driver, lambda p: len(p["captures"]) == 1 and p["button"],
                      "the list and the button with the page")
            take_capture(driver)
            taken = page_when(driver, lambda p: p["result"]["capture"] is not None,
                              "the capture taken", timeout=30)  # (burners: 15 s was short)
            assert taken["result"]["ok"] == "true"
            assert "recording, written in" in taken["result"]["text"]
            manual = page_when(driver, lambda p: len(p["captures"]) == 2,
                               "the manual capture listed")
            newest = manual["captures"][0]  # newest first
            assert (newest["id"], newest["trigger"], newest["alarm"]) == \
                (taken["result"]["capture"], "manual", None)
            assert [c["id"] for c in manual["captures"]] == \
                [c["id"] for c in get_json(f"{base}/api/v1/captures")]
            written = page_when(driver, lambda p: "written, in the list" in p["result"]["text"],
                                "the button's result says it is listed")
            assert written["result"]["text"] == \
                f"capture {newest['id']}: written, in the list below"
            screenshot(driver, tmp_path, "dashboard-captures.png")
            assert console_errors(driver) == []


def test_with_a_read_token_the_link_downloads_in_the_browser(tmp_path: Path) -> None:
    """Reads need a credential: a plain link could not send it, so the page fetches the
    ZIP with it; the file lands in the browser's download folder whole."""
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    with simulated([boom]) as line:
        cfg = config(line.path, tmp_path / "captures", {
            "token": TOKEN, "allow_commands": True, "read_token_required": True})
        with gateway(tmp_path, cfg, token=TOKEN) as base, chromium(tmp_path) as driver:
            driver.execute_cdp_cmd("Browser.setDownloadBehavior",
                                   {"behavior": "allow", "downloadPath": str(downloads)})
            log_in(driver, base, "", TOKEN, "admin")
            console_errors(driver)  # (GET /me's 401 before the login)
            page_when(driver, lambda p: p["mode"] == "on", "the captures' section")
            take_capture(driver)
            entry = page_when(driver, lambda p: len(p["captures"]) == 1,
                              "the capture listed")["captures"][0]
            assert httpx.get(entry["href"], timeout=10).status_code == 401  # no token
            download(driver, downloads)
            saved = downloads / entry["file"]
            # (a deadline: beside CPU burners and the rest of the suite, 15 s was short
            # once for Chromium to fetch the ZIP and write it)
            try:
                wait(saved.is_file, "the ZIP in the download folder", timeout=60)
            except AssertionError as exc:
                raise AssertionError(f"{exc}; the folder: {list(downloads.iterdir())}; "
                                     f"the page: {page(driver)}") from None
            archive = opened(saved.read_bytes())
            assert json.loads(archive.read("meta.json"))["trigger"]["reason"] == "manual"
            assert saved.stat().st_size == entry["size"]
            assert console_errors(driver) == []


def test_without_a_capture_section_a_note_and_no_error(tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([boom]) as line:
        cfg = config(line.path, tmp_path / "captures", {"token": TOKEN, "allow_commands": True})
        del cfg["capture"]
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            log_in(driver, base, "", TOKEN, "admin")
            off = page_when(driver, lambda p: p["mode"] == "off", "the note")
            assert off["note"] == ("Event capture is off: the gateway's config has no "
                                   'capture: section (docs/alarms.md, "Captures").')
            assert not off["listed"] and not off["button"]
            answer = httpx.get(f"{base}/api/v1/captures", timeout=5)
            assert answer.status_code == 404 and "no capture: section" in answer.json()["error"]
            # polls go on (two more rounds of the sensors' seq): still no error logged
            seq = get_json(f"{base}/api/v1/sensors/boom")["seq"]
            wait(lambda: get_json(f"{base}/api/v1/sensors/boom")["seq"] >= seq + 80,
                 "four seconds of samples")
            assert console_errors(driver) == []
