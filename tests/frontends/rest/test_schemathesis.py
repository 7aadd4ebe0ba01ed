"""schemathesis against the committed OpenAPI document and the live gateway (issue 6).

The gateway runs as its own process (``imu-gateway run``) on two simulated lines, with
commands allowed, so the generated requests reach real sensors.  Every check runs but
one: ``positive_data_acceptance`` expects every schema-valid request to succeed, and
the API (docs/rest.md) answers 422 to schema-valid commands a series lacks
(``clear_heading`` on an AH) or a protocol cannot carry, and 404 to a sensor name that
is not configured.
The live streams are left out (a stream never ends; tests/frontends/rest/test_rest.py covers them).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import httpx
import yaml
from support import ROOT
from support.harness import free_port

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

FAST = 115200


def test_schemathesis_finds_no_server_errors_or_schema_violations(tmp_path: Path) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST)
    port = free_port()
    with simulated([ah]) as line_a, simulated([vg]) as line_b:
        config = {
            "gateway_id": "st",
            "buses": [
                {"name": "a", "port": line_a.path, "baudrate": FAST, "protocol": "native",
                 "sensors": [{"name": "boom", "series": "AH"}]},
                {"name": "b", "port": line_b.path, "baudrate": FAST, "protocol": "modbus",
                 "sensors": [{"name": "arm", "series": "VG"}]}],
            "http": {"listen": f"127.0.0.1:{port}", "token": "tok", "allow_commands": True},
        }
        path = tmp_path / "gateway.yaml"
        path.write_text(yaml.safe_dump(config))
        with (tmp_path / "gateway.log").open("wb") as log:
            gateway = subprocess.Popen(
                [sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    if httpx.get(f"http://127.0.0.1:{port}/api/v1/health").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline, (tmp_path / "gateway.log").read_text()
                time.sleep(0.1)
            run = subprocess.run(
                [str(Path(sys.executable).parent / "schemathesis"), "run",
                 str(ROOT / "openapi" / "openapi.json"), "--url", f"http://127.0.0.1:{port}",
                 "--checks", "all", "--exclude-checks", "positive_data_acceptance",
                 "--header", "Authorization: Bearer tok",
                 # (Server-Sent Events never end: the live stream, traffic, a scan's)
                 "--exclude-path-regex", "stream|traffic|events",
                 "--max-examples", "20", "--generation-deterministic",
                 "--request-timeout", "15"],
                capture_output=True, text=True, timeout=100, cwd=tmp_path)
            assert run.returncode == 0, run.stdout[-8000:] + run.stderr[-2000:]
            assert gateway.poll() is None, "the gateway died"
        finally:
            gateway.terminate()
            code = gateway.wait(20)
        assert code == 0, (tmp_path / "gateway.log").read_text()[-3000:]
