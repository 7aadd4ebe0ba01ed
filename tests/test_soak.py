"""The soak (bench/soak.py, docs/reliability.md) in its shortest form: every fault and
hostile client once, with the minimum hold of 2 s, against the real gateway process,
mosquitto and the simulators.  About a minute; the 30-minute run is done by hand."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_short_soak_passes_every_check(tmp_path: Path) -> None:
    summary_file = tmp_path / "soak.json"
    # Its own timeout below the test's: on a loaded machine the recoveries take longer,
    # and the soak's own output is worth more than pytest-timeout's stack dump.
    soak = subprocess.Popen(
        [sys.executable, str(ROOT / "bench" / "soak.py"), "--minutes", "0.5", "--quiet",
         "--json", str(summary_file), "--keep", str(tmp_path / "files")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        start_new_session=True)
    try:
        stdout, stderr = soak.communicate(timeout=220)
    except subprocess.TimeoutExpired:
        # its gateway, simulators and broker go with it: left behind (as once), they
        # held their ports and CPU for the tests after this one
        os.killpg(soak.pid, signal.SIGKILL)
        stdout, stderr = soak.communicate()
        pytest.fail(f"the soak did not end within 220 s\nstdout:\n{stdout}\n"
                    f"stderr (end):\n{stderr[-3000:]}")
    report = f"stdout:\n{stdout}\nstderr (end):\n{stderr[-3000:]}"
    assert soak.returncode in (0, 1), report  # 2: it could not even be set up
    assert "RESULT: " in stdout, report
    summary = json.loads(summary_file.read_text())
    ran = {phase["name"] for phase in summary["phases"]}
    assert ran == set(summary["phases_planned"]), "every phase runs at least once"
    assert summary["final"]["alive"], report
    # the gateway's own count of late writes, per line, beside the simulators' view
    assert set(summary["final"]["late_writes"]) == set(summary["final"]["lines"]), report
    # The failures, one per line, are the message: which check and in which phase.
    assert soak.returncode == 0 and not summary["failures"], report


def test_the_soak_ends_a_client_that_lost_its_cancel() -> None:
    """A client whose cancel is lost (Python 3.11's ``wait_for`` can lose one that
    races its own timeout) is cancelled again until it ends: once, such a client held
    the soak until the test's timeout."""
    import asyncio
    import importlib.util

    spec = importlib.util.spec_from_file_location("hostile", ROOT / "bench" / "hostile.py")
    assert spec is not None and spec.loader is not None
    hostile = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("hostile", hostile)  # (its dataclasses look themselves up)
    spec.loader.exec_module(hostile)
    cancels = []

    async def stubborn() -> None:
        try:
            await asyncio.sleep(60)
        except asyncio.CancelledError:
            cancels.append("lost")  # as a lost cancel would be: it carries on
        await asyncio.sleep(60)

    async def main() -> None:
        task = asyncio.create_task(stubborn())
        await asyncio.sleep(0)
        await asyncio.wait_for(hostile.ended([task]), 10)
        assert task.cancelled() and cancels == ["lost"]

    asyncio.run(main())
