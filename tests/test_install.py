"""The gateway installed the way Python users install a tool: a wheel built from this
checkout (``python -m build``), installed into a fresh virtual environment outside the
checkout, and run from there: ``--version``, ``decode``, and ``demo`` answering its
dashboard, its API reference and a reading.

Nothing here imports from the checkout: the commands run in a directory of their own,
with the new environment's own Python, so a file missing from the wheel fails here.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.harness import free_port

from imu_gateway import __version__

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "build", "--wheel", "--outdir", str(out), str(ROOT)],
                   check=True, capture_output=True, timeout=300)
    (built,) = out.glob("imu_gateway-*.whl")
    return built


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``bin`` directory of a fresh venv with the wheel (and its dependencies)."""
    venv = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet",
                    "--disable-pip-version-check", str(wheel)],
                   check=True, capture_output=True, timeout=600)
    return venv / "bin"


def test_the_wheel_holds_the_package_data_and_nothing_of_the_checkout(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    assert "imu_gateway/py.typed" in names
    assert {"imu_gateway/static/index.html", "imu_gateway/static/dashboard.css"} <= set(names)
    # the examples `imu-gateway init --example NAME` writes
    assert {f"imu_gateway/examples/{name}.yaml" for name in
            ("single-native", "mixed-bus", "modbus-rtu-only")} <= set(names)
    assert not [n for n in names if n.startswith(("tests/", "bench/", "gateway/"))]
    assert any(n.endswith("licenses/LICENSE") for n in names)


def test_the_installed_command_runs_outside_the_checkout(installed: Path,
                                                         tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([str(installed / "imu-gateway"), *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=60)

    version = run("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"imu-gateway {__version__}"
    decoded = run("decode", "77 04 00 04 08")
    assert decoded.returncode == 0, decoded.stderr
    assert json.loads(decoded.stdout)["command"] == "read_angles"
    # python -m imu_gateway is the same command, in the installed copy
    module = subprocess.run([str(installed / "python"), "-m", "imu_gateway", "--version"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert module.stdout == version.stdout


@pytest.mark.slow
def test_pip_and_pipx_install_from_a_checkout(tmp_path: Path) -> None:
    """``pip install .`` into a venv, and ``pipx install .``: each gives a working
    ``imu-gateway`` on its PATH."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    subprocess.run([str(venv / "bin" / "pip"), "install", "--quiet",
                    "--disable-pip-version-check", "."], cwd=ROOT, check=True,
                   capture_output=True, timeout=600)
    pipx_bin = tmp_path / "pipx-bin"
    env = {**os.environ, "PIPX_HOME": str(tmp_path / "pipx"), "PIPX_BIN_DIR": str(pipx_bin),
           "PIPX_MAN_DIR": str(tmp_path / "man")}
    subprocess.run([sys.executable, "-m", "pipx", "install", "."], cwd=ROOT, env=env,
                   check=True, capture_output=True, timeout=600)
    for command in (venv / "bin" / "imu-gateway", pipx_bin / "imu-gateway"):
        done = subprocess.run([str(command), "--version"], cwd=tmp_path, capture_output=True,
                              text=True, timeout=60)
        assert done.stdout.strip() == f"imu-gateway {__version__}", (command, done)


@pytest.fixture
def demo(installed: Path, tmp_path: Path) -> Iterator[str]:
    http_port, modbus_port = free_port(), free_port()
    process = subprocess.Popen(
        [str(installed / "imu-gateway"), "demo", "--http-port", str(http_port),
         "--modbus-port", str(modbus_port)],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert process.stdout is not None
        for line in process.stdout:  # the banner says when it is ready
            if line.startswith("Stop with Ctrl-C"):
                break
        else:
            pytest.fail("the installed demo ended before its banner")
        yield f"http://127.0.0.1:{http_port}"
    finally:
        process.terminate()
        code = process.wait(30)
        assert process.stdout is not None
        process.stdout.close()
        assert code == 0


def test_the_installed_demo_serves_its_dashboard_docs_and_readings(demo: str) -> None:
    dashboard = httpx.get(f"{demo}/")
    assert dashboard.status_code == 200 and "imu-gateway" in dashboard.text
    assert httpx.get(f"{demo}/static/dashboard.js").status_code == 200
    docs = httpx.get(f"{demo}/docs")
    assert docs.status_code == 200
    assert httpx.get(f"{demo}/docs/assets/swagger-ui-bundle.js").status_code == 200
    sensors = httpx.get(f"{demo}/api/v1/sensors").json()
    name = sensors[0]["name"]
    deadline = time.monotonic() + 30
    while (reading := httpx.get(f"{demo}/api/v1/sensors/{name}/reading").json())["seq"] < 1:
        assert time.monotonic() < deadline, reading
        time.sleep(0.1)
    assert reading["sensor"] == name and reading["status"] == "ok"
