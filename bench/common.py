"""What the benchmarks share: free ports, and the simulator and the gateway as
processes of their own (as in a plant, they share no interpreter with the load)."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def processes(sensor_yaml: str, interfaces_yaml: str, *others: list[str],
              baud: int = 115200) -> Iterator[None]:
    """A simulated native AH on a pty, ``imu-gateway run`` with one bus of that
    sensor (``sensor_yaml``: its YAML mapping, ``{name: boom, series: AH, …}``) and the
    interfaces of ``interfaces_yaml``, and ``others`` (further commands), until the
    block ends."""
    python = sys.executable
    simulator = subprocess.Popen(
        [python, "-m", "imu_gateway", "simulate", "--protocol", "native", "--series", "AH",
         "--baud", str(baud)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert simulator.stdout is not None
    pty = simulator.stdout.readline().split()[1]
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "bench.yaml"
        config.write_text(f"""
buses:
  - name: bench
    port: {pty}
    baudrate: {baud}
    protocol: native
    sensors: [{sensor_yaml}]
{interfaces_yaml}
""")
        procs = [subprocess.Popen([python, "-m", "imu_gateway", "run", "-c", str(config),
                                   "--log-level", "warning"]),
                 *(subprocess.Popen(cmd, stderr=subprocess.DEVNULL) for cmd in others)]
        try:
            yield
        finally:
            running: list[subprocess.Popen[bytes] | subprocess.Popen[str]] = [*procs, simulator]
            for proc in running:
                proc.terminate()
                proc.wait(10)
