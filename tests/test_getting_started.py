"""docs/getting-started.md, followed word by word: its commands, read from the guide
itself, run against the simulator, and what they print compared with what the guide
shows.

The simulator stands in for the sensor and its adapter: a native AH at address 0 and
9600 baud, answering 5-40 ms late, on a pseudo-terminal whose path takes the place of
the guide's ``/dev/serial/by-id/…`` name.  Free ports take the place of 5020, 8080
and 1883 (a test must not take a machine's own), and a mosquitto started here is the
guide's broker.  Nothing else in a command is changed.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.broker import Mosquitto
from support.harness import free_port

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimulatorThread, make_sensor

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "getting-started.md"
BIN = ROOT / ".venv" / "bin"
DEVICE = "/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A10KZP3Q-if00-port0"


def section(number: int) -> str:
    text = GUIDE.read_text(encoding="utf-8")
    match = re.search(rf"^## {number}\. .*?(?=^## |\Z)", text, re.M | re.S)
    assert match, f"no section {number}"
    return match.group(0)


def blocks(number: int, language: str = "") -> list[str]:
    """The code blocks of a section in ``language`` (none: plain), dedented (a block in
    a list item is indented)."""
    found: list[str] = []
    body: list[str] | None = None
    for line in section(number).splitlines():
        fence = line.strip().startswith("```")
        if body is None and fence:
            body = [] if line.strip() == f"```{language}" else None
            if body is None:
                body = ["\0"]  # another language: skipped, but its fences still pair
        elif body is not None and fence:
            if body[:1] != ["\0"]:
                found.append(textwrap.dedent("\n".join(body) + "\n"))
            body = None
        elif body is not None:
            body.append(line)
    return found


class Guide:
    """The substitutions: the simulated port and free ports for the guide's."""

    def __init__(self, port: str, mqtt_port: int) -> None:
        self.swaps = {DEVICE: port, "5020": str(free_port()), "8080": str(free_port()),
                      "1883": str(mqtt_port)}

    def __call__(self, text: str) -> str:
        for old, new in self.swaps.items():
            text = text.replace(old, new)
        return text

    def argv(self, line: str) -> list[str]:
        argv = shlex.split(self(line))
        if argv[0] == "imu-gateway":
            argv[0] = str(BIN / "imu-gateway")  # the checkout's, as scripts/run runs it
        return argv


@pytest.fixture
def guide(tmp_path: Path) -> Iterator[Guide]:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=9600, answer_delay=0.005,
                         jitter=0.035)
    with SimulatorThread([sensor]) as line, Mosquitto(tmp_path) as broker:
        yield Guide(line.path, broker.port)


def _shown(block: str) -> tuple[str, list[str]]:
    """A ``$ command`` block: the command, and the lines the guide shows it print."""
    first, *rest = block.strip("\n").split("\n")
    assert first.startswith("$ "), first
    return first[2:], rest


def test_step_0_the_checkout_runs_without_installing() -> None:
    (block,) = [b for b in blocks(0) if "scripts/run" in b]
    done = subprocess.run(shlex.split(block.strip()), cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert re.fullmatch(r"imu-gateway \d+\.\d+\.\d+\S*\n", done.stdout)


def test_steps_4_to_7_on_the_simulator(guide: Guide, tmp_path: Path) -> None:
    # 4. the scan finds the sensor the guide shows, and says the same
    (scan,) = [b for b in blocks(4) if b.startswith("$ imu-gateway scan")]
    command, shown = _shown(scan)
    done = subprocess.run(guide.argv(command), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    # (the guide shows stdout and stderr as a terminal mixes them)
    printed = done.stdout.splitlines() + done.stderr.splitlines()
    assert {guide(line) for line in shown} == set(printed), (shown, printed)

    # 5. the config, written as shown, passes the check the guide shows
    (config,) = blocks(5, "yaml")
    (tmp_path / "gateway.yaml").write_text(guide(config))
    (check,) = [b for b in blocks(5) if b.startswith("$ imu-gateway check-config")]
    command, shown = _shown(check)
    done = subprocess.run(guide.argv(command), cwd=tmp_path, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and done.stdout.splitlines() == shown, done

    # 6. run: the log lines the guide shows come, in its words
    (run,) = [b for b in blocks(6) if b.startswith("$ imu-gateway run")]
    command, shown = _shown(run)
    # the one change to a command: the statistics every 2 s, not every minute, so the
    # line the guide shows comes while the test waits
    command = command.replace("--stats-interval 60", "--stats-interval 2")
    log = (tmp_path / "run.log").open("w+")
    process = subprocess.Popen(guide.argv(command), cwd=tmp_path, stdout=log,
                               stderr=subprocess.STDOUT, text=True)
    try:
        _expect_log(guide, shown, tmp_path / "run.log")
        _expect_stats(shown, tmp_path / "run.log")
        _step_7(guide)
    finally:
        process.terminate()
        assert process.wait(30) == 0
        log.close()


def _expect_log(guide: Guide, shown: list[str], path: Path) -> None:
    """Each line the guide shows, "…" standing for the time and a long path; the
    statistics line is left out (it comes after a minute, with other figures)."""
    shown = [line.replace("/dev/serial/by-id/…", DEVICE) for line in shown]  # abridged
    patterns = [re.escape(guide(line).removeprefix("… ")).replace("…", ".*")
                for line in shown if "transactions/s" not in line]
    deadline = time.monotonic() + 30
    while True:
        text = path.read_text()
        missing = [p for p in patterns if not re.search(p, text)]
        if not missing:
            return
        assert time.monotonic() < deadline, (missing, text)
        time.sleep(0.1)


STATS = re.compile(r"bus line-a: ([\d.]+) transactions/s, utilisation ([\d.]+), errors none")
#: what the run prints: the same, with whatever errors it counted
PRINTED = re.compile(r"bus line-a: ([\d.]+) transactions/s, utilisation ([\d.]+), errors ")


def _expect_stats(shown: list[str], path: Path) -> None:
    """The statistics line the guide shows, in figures the run prints: a span (after
    the first, which starts mid-way) with the rate within 0.3/s and the utilisation
    within 0.05 of the guide's (the guide says they move with the sensor's answer
    delays; the simulator's are the 5-40 ms of this module's docstring).  Waited for,
    not taken from the first spans: on a busy machine a span is slower, or holds an
    answer garbled while the simulator was held, and the next one is as the guide."""
    (line,) = [line for line in shown if "transactions/s" in line]
    expected = STATS.search(line)
    assert expected, line
    want_rate, want_utilisation = float(expected.group(1)), float(expected.group(2))

    def matches() -> bool:
        return any(abs(float(r) - want_rate) <= 0.3 and abs(float(u) - want_utilisation)
                   <= 0.05 for r, u in PRINTED.findall(path.read_text())[1:])

    deadline = time.monotonic() + 60
    while not matches():
        assert time.monotonic() < deadline, (line, path.read_text())
        time.sleep(0.1)


def _step_7(guide: Guide) -> None:
    """7: each interface answers the guide's own commands as the guide shows."""
    curls = [line for b in blocks(7) for line in b.splitlines() if line.startswith("curl ")]
    health = subprocess.run(guide.argv(curls[0]), capture_output=True, text=True, timeout=30)
    assert json.loads(health.stdout)["gateway_id"] == "bench-1"
    reading: dict[str, object] = {}
    deadline = time.monotonic() + 30
    while reading.get("status") != "ok":
        assert time.monotonic() < deadline, reading
        got = subprocess.run(guide.argv(curls[1]), capture_output=True, text=True, timeout=30)
        reading = json.loads(got.stdout)
        time.sleep(0.1)
    shown = next(b for b in blocks(7, "json"))
    assert set(re.findall(r'"(\w+)":', shown)) <= _keys(reading)

    (mbpoll,) = [b.strip() for b in blocks(7) if b.startswith("mbpoll ")]
    out = subprocess.run(guide.argv(mbpoll), capture_output=True, text=True, timeout=30).stdout
    registers = re.findall(r"^\[(\d+)\]:\s+(\S+)", out, re.M)
    assert [r for r, _ in registers] == ["101", "103", "105", "107", "109", "111"], out

    (sub,) = [b.strip() for b in blocks(7) if b.startswith("mosquitto_sub ")]
    shown_topics = [line.split()[0] for b in blocks(7) for line in b.splitlines()
                    if line.startswith("imu/")]
    out = subprocess.run([*guide.argv(sub), "-W", "10", "-C", "10"], capture_output=True,
                         text=True, timeout=30).stdout
    assert set(shown_topics) <= {line.split()[0] for line in out.splitlines()}, out


def _keys(value: object) -> set[str]:
    if isinstance(value, dict):
        return set(value) | {k for v in value.values() for k in _keys(v)}
    return set()


def test_the_guide_names_no_other_device_or_port() -> None:
    """The substitutions above are the only ones the guide needs: one device path,
    and the three ports."""
    text = GUIDE.read_text(encoding="utf-8")
    devices = set(re.findall(r"/dev/serial/by-id/[\w.-]+", text))
    assert devices == {DEVICE}
    for section_number in (5, 6, 7):
        ports = set(re.findall(r":(\d{4})\b|-p (\d{4})\b", section(section_number)))
        assert {p for pair in ports for p in pair if p} <= {"5020", "8080", "1883"}
