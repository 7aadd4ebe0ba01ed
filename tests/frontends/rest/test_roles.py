"""Roles over REST (docs/rest.md, "Roles"), from the side of a client that tries to do
more than its role lets it: every route of the OpenAPI document declares its role, and
a client one role lower is refused (401 without a credential, 403 with too low a
role); the old single ``http.token`` is an admin's; a login gives a session that a
logout ends; login attempts are limited per address, and an attacker's lockout is not
anybody else's.  A real gateway on a simulated sensor, a real HTTP client."""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from support.harness import running, until

from imu_gateway.config import HttpConfig
from imu_gateway.frontends.rest.access import MAX_SESSIONS, Authority, Role, Roles, Who
from imu_gateway.frontends.rest.routes import create_app
from imu_gateway.model import Series, WireProtocol
from imu_gateway.passwords import hash_password
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

API = "/api/v1"
FAST = 115200
TOKENS = {"viewer": "view-t0ken", "operator": "op-t0ken", "admin": "admin-t0ken"}
PASSWORDS = {"vera": "vera's password", "otto": "otto's password"}
USERS = {"vera": {"role": "viewer", "password": hash_password(PASSWORDS["vera"])},
         "otto": {"role": "operator", "password": hash_password(PASSWORDS["otto"])}}
#: The role one lower than each (``None``: no credential at all).
LOWER = {"viewer": None, "operator": "viewer", "admin": "operator"}
#: A value for each path parameter of the document (a refusal comes before they matter).
PARAMS = {"name": "boom", "sensor": "boom", "alarm": "boom_lean", "capture_id": "x",
          "command": "save", "procedure": "zero", "run_id": "1", "bus": "a", "scan_id": "1"}


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture
def line() -> Iterator[str]:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST,
                      source=hold(Motion.from_seed(3).sample(10.0)))
    with simulated([sim]) as bus:
        yield bus.path


def config(port: str, **http: Any) -> dict[str, Any]:
    return {"gateway_id": "roles", "buses": [{
        "name": "a", "port": port, "baudrate": FAST, "protocol": "native", "timeout_ms": 300,
        "sensors": [{"name": "boom", "series": "AH", "alarms": [
            {"name": "boom_lean", "field": "pitch", "above": 80}]}]}],
        "http": {"listen": "127.0.0.1:0", **http}}


def roles_config(port: str) -> dict[str, Any]:
    return config(port, tokens=[{"token": t, "role": r} for r, t in TOKENS.items()],
                  users=USERS, allow_commands=True, read_token_required=True)


def client(gateway: Any, **options: Any) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10,
                             **options)


def operations(document: dict[str, Any]) -> Iterator[tuple[str, str, str | None]]:
    for path, item in document["paths"].items():
        for method, operation in item.items():
            yield method.upper(), path, operation.get("x-role")


@pytest.mark.anyio
async def test_every_route_declares_a_role_and_refuses_a_lower_one(line: str) -> None:
    """A table over the served OpenAPI document: a route without ``x-role`` fails here,
    so a new route must say who may call it.  One role lower: 403 (no credential: 401);
    the role itself gets past the rule (a GET answers neither 401 nor 403)."""
    async with running(roles_config(line)) as gateway, client(gateway) as http:
        document = (await http.get("/openapi.json")).json()
        table = list(operations(document))
        assert len(table) >= 20
        undeclared = [f"{m} {p}" for m, p, role in table if role is None]
        assert undeclared == [], f"routes without a declared role: {undeclared}"
        declared = {f"{m} {p}": role for m, p, role in table}
        assert declared[f"POST {API}/login"] == "public"
        assert declared[f"GET {API}/sensors"] == "viewer"
        assert declared[f"POST {API}/alarms/{{sensor}}/{{alarm}}/ack"] == "operator"
        assert declared[f"POST {API}/sensors/{{name}}/commands/save"] == "operator"
        assert declared[f"POST {API}/captures"] == "operator"
        assert declared[f"GET {API}/config"] == declared[f"PUT {API}/config"] == "admin"
        assert declared[f"POST {API}/sensors/{{name}}/procedures/{{procedure}}"] == "operator"
        assert declared[f"GET {API}/sensors/{{name}}/procedures"] == "viewer"
        assert declared[f"POST {API}/scan"] == "admin"
        assert declared[f"GET {API}/buses/{{bus}}/traffic"] == "viewer"
        for method, path, role in table:
            if role == "public":
                continue
            url = re.sub(r"\{(\w+)\}", lambda m: PARAMS[m.group(1)], path)
            lower = LOWER[role or ""]
            headers = bearer(TOKENS[lower]) if lower else {}
            refused = await http.request(method, url, headers=headers)
            want = 403 if lower else 401
            assert refused.status_code == want, (method, path, role, refused.text)
            assert refused.json()["kind"] == ("forbidden" if lower else "unauthorised")
            if method == "GET":
                async with http.stream(method, url, headers=bearer(TOKENS[role or ""])) as ok:
                    assert ok.status_code not in (401, 403), (method, path, role)


@pytest.mark.anyio
async def test_the_old_single_token_is_an_admins(line: str) -> None:
    """A config of before roles (``http.token`` only) keeps working: that token runs
    commands and acknowledges, and is an admin's; without it, refused as before."""
    async with running(config(line, token="old-t0ken", allow_commands=True)) as gateway, \
            client(gateway) as http:
        me = await http.get(f"{API}/me", headers=bearer("old-t0ken"))
        assert me.json() == {"user": "http.token", "role": "admin"}
        command = f"{API}/sensors/boom/commands/read_settings"
        assert (await http.post(command)).status_code == 401
        done = await http.post(command, headers=bearer("old-t0ken"))
        assert done.status_code == 200, done.text
        ack = await http.post(f"{API}/alarms/boom/boom_lean/ack", headers=bearer("old-t0ken"))
        assert ack.json()["kind"] == "nothing_to_acknowledge"  # past the rule: the alarm is normal
        # Reads stay open without read_token_required, as before.
        assert (await http.get(f"{API}/sensors")).status_code == 200


@pytest.mark.anyio
async def test_a_login_gives_a_session_a_logout_ends_it(line: str) -> None:
    async with running(roles_config(line)) as gateway, client(gateway) as http:
        wrong = await http.post(f"{API}/login", json={"user": "otto", "password": "guess"})
        assert wrong.status_code == 401 and wrong.json()["kind"] == "unauthorised"
        nobody = await http.post(f"{API}/login", json={"user": "nobody", "password": "x"})
        assert nobody.status_code == 401
        assert wrong.json()["error"] == nobody.json()["error"]  # no hint which names exist
        logged = await http.post(f"{API}/login",
                                 json={"user": "otto", "password": PASSWORDS["otto"]})
        assert logged.status_code == 200, logged.text
        session = logged.json()
        assert (session["user"], session["role"]) == ("otto", "operator")
        assert session["expires_at"].endswith("Z") and len(session["token"]) >= 40
        otto = bearer(session["token"])
        assert (await http.get(f"{API}/me", headers=otto)).json() == {
            "user": "otto", "role": "operator"}
        ack = await http.post(f"{API}/alarms/boom/boom_lean/ack", headers=otto)
        assert ack.json()["kind"] == "nothing_to_acknowledge"  # past the rule
        assert (await http.post(f"{API}/logout", headers=otto)).status_code == 204
        for after in (await http.get(f"{API}/me", headers=otto),
                      await http.get(f"{API}/sensors", headers=otto),
                      await http.post(f"{API}/alarms/boom/boom_lean/ack", headers=otto)):
            assert after.status_code == 401, after.text
        # A viewer's session reads, and may not acknowledge.
        vera = (await http.post(f"{API}/login", json={
            "user": "vera", "password": PASSWORDS["vera"]})).json()
        assert (await http.get(f"{API}/sensors", headers=bearer(vera["token"]))).is_success
        refused = await http.post(f"{API}/alarms/boom/boom_lean/ack",
                                  headers=bearer(vera["token"]))
        assert refused.status_code == 403 and "vera" in refused.json()["error"]
        # A token of the config logs in as itself, and does not expire.
        as_token = await http.post(f"{API}/login", json={"token": TOKENS["admin"]})
        assert as_token.json() == {"token": TOKENS["admin"], "user": "token 3 of http.tokens",
                                   "role": "admin", "expires_at": None}


@pytest.mark.anyio
async def test_login_attempts_are_limited_per_address(line: str) -> None:
    """An attacker at 127.0.0.2 guesses: the sixth attempt in a minute is 429 with
    Retry-After, even with the right password (the guessing stops); a user at
    127.0.0.1 logs in meanwhile."""
    async with running(roles_config(line)) as gateway, \
            client(gateway, transport=httpx.AsyncHTTPTransport(
                local_address="127.0.0.2")) as attacker, client(gateway) as user:
        for n in range(5):
            guess = await attacker.post(f"{API}/login",
                                        json={"user": "otto", "password": f"guess{n}"})
            assert guess.status_code == 401, guess.text
        for password in ("guess5", PASSWORDS["otto"]):
            stopped = await attacker.post(f"{API}/login",
                                          json={"user": "otto", "password": password})
            assert stopped.status_code == 429, stopped.text
            assert stopped.json()["kind"] == "too_many_attempts"
            assert 1 <= int(stopped.headers["Retry-After"]) <= 60
        mine = await user.post(f"{API}/login", json={"user": "otto",
                                                      "password": PASSWORDS["otto"]})
        assert mine.status_code == 200, mine.text
        # A body too large for a login is refused before it is read.
        huge = await user.post(f"{API}/login", content=b"x" * 100_000,
                               headers={"Content-Type": "application/json"})
        assert huge.status_code == 413


@pytest.mark.anyio
async def test_every_admin_action_is_logged_with_who(line: str,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    """An admin's route (none is in this build's API yet: one added as a new route
    would be, with ``roles.admin``) logs who called it; an operator is refused."""
    async with running(roles_config(line)) as gateway:
        assert gateway.http is not None
        app = create_app(gateway, gateway.config.http)  # type: ignore[arg-type]
        roles: Roles = app.state.roles

        @app.put(f"{API}/admin-thing", dependencies=[roles.admin])
        async def admin_thing() -> dict[str, bool]:
            return {"done": True}

        transport = httpx.ASGITransport(app=app, client=("10.0.0.9", 5555))
        async with httpx.AsyncClient(transport=transport, base_url="http://gw") as http:
            refused = await http.put(f"{API}/admin-thing", headers=bearer(TOKENS["operator"]))
            assert refused.status_code == 403
            with caplog.at_level(logging.INFO, logger="imu_gateway.http"):
                done = await http.put(f"{API}/admin-thing", headers=bearer(TOKENS["admin"]))
            assert done.status_code == 200
        await until(lambda: any("admin" in r.getMessage() for r in caplog.records))
        assert [r.getMessage() for r in caplog.records if r.name == "imu_gateway.http"] == [
            f"admin token 3 of http.tokens (10.0.0.9): PUT {API}/admin-thing"]


def test_a_session_ends_when_it_expires_and_the_oldest_goes_first(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``http.session_minutes`` after its login a session's token is nobody's; past
    ``MAX_SESSIONS`` the oldest session ends (a flood of logins cannot grow memory)."""
    authority = Authority(HttpConfig(session_minutes=1))
    otto = Who("otto", Role.OPERATOR)
    token, expires_at = authority.start_session(otto)
    assert authority.who(token) == otto and expires_at > time.time() + 59
    start = time.monotonic()
    monkeypatch.setattr(time, "monotonic", lambda: start + 59)
    assert authority.who(token) == otto
    monkeypatch.setattr(time, "monotonic", lambda: start + 61)
    assert authority.who(token) is None and token not in authority.sessions
    monkeypatch.undo()
    first = authority.start_session(otto)[0]
    for _ in range(MAX_SESSIONS):
        authority.start_session(otto)
    assert len(authority.sessions) == MAX_SESSIONS and authority.who(first) is None
