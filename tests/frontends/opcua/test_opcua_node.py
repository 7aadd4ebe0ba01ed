"""The OPC UA server against Node's node-opcua (tests/node/opcua.js), a client that
knows it only from docs/opcua.md: browse, read, subscribe, read history, call, and be
refused."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID
from support import ROOT
from support.harness import expected, free_port, running, tolerance, until

import imu_gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

NODE_DIR = ROOT / "tests" / "node"
GID = "ua-node"
READING = Motion.from_seed(12).sample(2.0)


async def node_opcua(*args: str, certificate: tuple[Path, Path], mode: str = "None",
                     script: str = "opcua.js") -> dict[str, Any]:
    """node-opcua's client (``script`` in tests/node) with this certificate and key
    (PEM), in this mode."""
    node = shutil.which("node")
    assert node is not None, "node is needed: scripts/bootstrap --test installs it"
    assert (NODE_DIR / "node_modules" / "node-opcua-client").is_dir(), \
        "run scripts/bootstrap --test (npm ci in tests/node)"
    proc = await asyncio.create_subprocess_exec(
        node, str(NODE_DIR / script), *args, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={"NODE_PATH": str(NODE_DIR / "node_modules"), "UA_CERT": str(certificate[0]),
             "UA_KEY": str(certificate[1]), "UA_MODE": mode,
             "HOME": str(certificate[0].parent)})  # node-opcua's own PKI folder goes there
    out, err = await asyncio.wait_for(proc.communicate(), 90)
    assert proc.returncode == 0, err.decode()[-2000:]
    (line,) = [x for x in out.decode().splitlines() if x.startswith("RESULT ")]
    answer: dict[str, Any] = json.loads(line.removeprefix("RESULT "))
    return answer


async def trusted_client(tmp_path: Path, pki: Path) -> tuple[Path, Path]:
    """A client certificate (PEM) and key, put in the server's trust list."""
    folder = tmp_path / "client"
    folder.mkdir()
    key, der = folder / "key.pem", folder / "cert.der"
    await setup_self_signed_certificate(
        key, der, "urn:test:node-opcua", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "node-opcua test client"})
    cert = x509.load_der_x509_certificate(der.read_bytes())
    pem = folder / "cert.pem"
    pem.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (pki / "trusted").mkdir(parents=True, exist_ok=True)
    (pki / "trusted" / "node-opcua.der").write_bytes(der.read_bytes())
    return pem, key


def _config(port: int, pki: Path, line: str, **opcua: Any) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20}]}],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki), "allow_none": True,
                      **opcua}}


async def watch_quality(endpoint: str, node_id: str, certificate: tuple[Path, Path],
                        stall: Faults) -> list[str]:
    """node-opcua subscribed to ``node_id`` (tests/node/opcua_quality.js) while the
    sensor stalls: the StatusCodes it is told of, until BadCommunicationError."""
    node = shutil.which("node")
    assert node is not None
    watcher = await asyncio.create_subprocess_exec(
        node, str(NODE_DIR / "opcua_quality.js"), endpoint, node_id,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
        env={"NODE_PATH": str(NODE_DIR / "node_modules"), "UA_CERT": str(certificate[0]),
             "UA_KEY": str(certificate[1]), "HOME": str(certificate[0].parent)})
    assert watcher.stdout is not None
    stdout = watcher.stdout
    seen: list[str] = []

    async def until_seen(status: str) -> None:
        while status not in seen:
            line = (await stdout.readline()).decode()
            assert line, f"node-opcua ended; it saw {seen}"
            if line.startswith("STATUS "):
                seen.append(line.split()[1])

    try:
        await asyncio.wait_for(until_seen("Good"), 30)
        stall.stalled = True
        await asyncio.wait_for(until_seen("BadCommunicationError"), 60)
    finally:
        watcher.kill()
        await watcher.wait()
    return seen


@pytest.mark.anyio
async def test_node_opcua_browses_reads_subscribes_and_sees_the_quality(
        tmp_path: Path) -> None:
    faults = Faults()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING),
                     faults=faults)
    port = free_port()
    client = await trusted_client(tmp_path, tmp_path / "pki")
    endpoint = f"opc.tcp://127.0.0.1:{port}/"
    with simulated([ah]) as line:
        cfg = _config(port, tmp_path / "pki", line.path)
        cfg["buses"][0]["sensors"][0]["stale_after_ms"] = 400
        async with running(cfg) as gw:
            # (some seconds of history first: seconds must pass, a deadline well past them)
            await until(lambda: len(gw.history.seconds("boom", "pitch")) >= 4, timeout=30)
            got = await node_opcua(endpoint, GID, "boom", certificate=client)
            assert gw.opcua is not None
            pitch = f"ns={gw.opcua.idx};s={GID}.Sensors.boom.Angles.pitch"
            quality = await watch_quality(endpoint, pitch, client, faults)
    # Good, then stale (its last usable value), then offline
    assert quality.index("Good") < quality.index("UncertainLastUsableValue") \
        < quality.index("BadCommunicationError"), quality
    assert got["sensors"] == ["boom"]
    assert {"Angles", "MagneticField", "Status", "Sequence"} <= set(got["children"])
    for name, value in expected(ah).items():
        seen = got["values"][name]
        assert seen["status"] == "Good"
        slack = tolerance(WireProtocol.NATIVE, name, value) + 1e-6 * max(1, abs(value))
        assert abs(seen["value"] - value) <= slack, (name, seen, value)
    _check_history(got["history"], expected(ah)["pitch"])
    numbers = [n["value"] for n in got["notifications"]]
    sources = [n["source"] for n in got["notifications"]]
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers) >= 5
    assert sources == sorted(sources)


def _check_history(history: dict[str, Any], pitch: float) -> None:
    """node-opcua's history of the held pitch: raw values Good, at increasing wire
    times; Minimum and Maximum per second stamped at each second, Good + Calculated."""
    slack = tolerance(WireProtocol.NATIVE, "pitch", pitch) + 1e-6 * max(1, abs(pitch))
    raw = history["raw"]
    assert raw["status"] == 0, raw
    # node-opcua asks for the bounds: none before the gateway started, maybe one at the
    # end (a second newer than the client's clock)
    first, *kept = raw["values"]
    assert first["status"] == ua.StatusCodes.BadBoundNotFound, raw
    if kept[-1]["status"] == ua.StatusCodes.BadBoundNotFound:
        kept.pop()
    assert kept and all(v["status"] == 0 and abs(v["value"] - pitch) <= slack
                        for v in kept), raw
    sources = [v["source"] for v in raw["values"]]
    assert sources == sorted(sources)
    for name in ("minimum", "maximum"):
        got = history[name]
        assert got["status"] == 0, got
        assert [v["source"] for v in got["values"]] == [history["start"] + 1000 * k
                                                         for k in range(3)]
        assert all(v["status"] == 0x401 and abs(v["value"] - pitch) <= slack
                   for v in got["values"]), (got, pitch)


@pytest.mark.anyio
async def test_node_opcua_needs_a_user_and_then_calls_a_method(tmp_path: Path) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    port = free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}/"
    cfg = _config(port, tmp_path / "pki", "", anonymous=False, allow_commands=True,
                  users={"operator": "s3cret"})
    cfg["opcua"]["allow_none"] = False  # Basic256Sha256 SignAndEncrypt only
    client = await trusted_client(tmp_path, tmp_path / "pki")
    with simulated([ah]) as line:
        cfg["buses"][0]["port"] = line.path
        async with running(cfg) as gw:
            await until(lambda: gw.cache.snapshot("boom").seq >= 2)
            # (a wrong password, an unknown user and mode None are refused in
            # test_opcua.py with asyncua's client: each node-opcua run costs seconds)
            secure = "SignAndEncrypt"
            refused = await node_opcua(endpoint, GID, "boom", certificate=client, mode=secure)
            allowed = await node_opcua(endpoint, GID, "boom", "operator", "s3cret",
                                       certificate=client, mode=secure)
    assert "refused" in refused, refused
    assert allowed["call"]["status"] == "Good"
    assert allowed["call"]["result"][0].startswith("set_zero_type: ok")
    assert ah.settings.zero_type == "relative"


@pytest.mark.anyio
async def test_node_opcua_reads_build_info_the_type_and_our_node_ids(tmp_path: Path) -> None:
    """What node-opcua's client finds: the gateway's BuildInfo, each sensor an
    ImuSensorType with its modelling rules, EURange and EngineeringUnits by browse path
    at NodeIds of the gateway's namespace, and Part 4's codes for calls of the wrong
    shape (the sensor hearing none of them)."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    port = free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}/"
    client = await trusted_client(tmp_path, tmp_path / "pki")
    with simulated([ah]) as line:
        cfg = _config(port, tmp_path / "pki", line.path, anonymous=False,
                      allow_commands=True, users={"operator": "s3cret"})
        async with running(cfg) as gw:
            await until(lambda: gw.cache.snapshot("boom").seq >= 1)
            got = await node_opcua(endpoint, GID, "boom", "operator", "s3cret",
                                   certificate=client, script="opcua_model.js")
    assert got["build"]["productName"] == "imu-gateway"
    assert got["build"]["softwareVersion"] == imu_gateway.__version__
    assert got["build"]["buildNumber"] and not got["build"]["buildDate"].startswith("1601")
    ns = got["ns"]
    assert got["type"]["name"] == "ImuSensorType"
    assert got["type"]["nodeId"] == f"ns={ns};s=ImuSensorType"
    assert got["type"]["supertype"] == "BaseObjectType"
    rules = got["type"]["declarations"]
    assert rules["Acceleration"] == rules["Status"] == "Mandatory"
    assert rules["MagneticField"] == rules["set_declination"] == "Optional"
    pitch = f"ns={ns};s={GID}.Sensors.boom.Angles.pitch"
    assert got["properties"] == {"EURange": [f"{pitch}.EURange"],
                                 "EngineeringUnits": [f"{pitch}.EngineeringUnits"]}
    assert got["calls"]["tooMany"]["status"] == "BadTooManyArguments"
    assert got["calls"]["missing"]["status"] == "BadArgumentsMissing"
    assert got["calls"]["wrongType"] == {"status": "BadInvalidArgument",
                                         "inputs": ["BadTypeMismatch"]}
    assert not ah.writes_heard and ah.settings.declination == 0.0
