"""How late the simulator hears what the gateway wrote: the pseudo-terminal's hand-over.

A pseudo-terminal passes bytes from one end to the other through a kernel worker that
runs at normal priority, so on a loaded machine the simulated sensor may hear a
request later than it was written: a delay a real UART does not add on the way out.
This prints, for one AH polled flat out at 115200 baud in one process, the delay from
the gateway's ``write()`` to the simulator reading the bytes.  Run it beside your load
(``stress-ng --cpu 4 & python bench/ptylag.py --seconds 20``) to see how much of a
collision seen under load the test bench itself may have made.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from support.harness import running

from imu_gateway.bus.link import SerialLink
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.bus import LineLog


class Timings:
    """When each request was written, and when the simulator heard one."""

    def __init__(self) -> None:
        self.written: list[float] = []
        self.heard: list[float] = []

    def install(self) -> None:
        write, timeline = SerialLink.write, LineLog.timeline

        def timed_write(link: SerialLink, data: bytes, *args: Any, **kwargs: Any) -> bool:
            self.written.append(time.monotonic())
            return write(link, data, *args, **kwargs)

        def timed_timeline(log: LineLog, text: str) -> None:
            if text.startswith("master ->"):
                self.heard.append(time.monotonic())
            timeline(log, text)

        SerialLink.write = timed_write  # type: ignore[method-assign,assignment]
        LineLog.timeline = timed_timeline  # type: ignore[method-assign,assignment]

    def report(self) -> str:
        n = min(len(self.written), len(self.heard))
        lags = sorted(h - w for w, h in zip(self.written[:n], self.heard[:n], strict=True))
        if not lags:
            return "no request was heard"

        def ms(q: float) -> float:
            return lags[int(q * (len(lags) - 1))] * 1000

        return (f"{n} requests: write -> heard median {ms(0.5):.2f} ms, p99 {ms(0.99):.2f} "
                f"ms, p99.9 {ms(0.999):.2f} ms, max {lags[-1] * 1000:.2f} ms; over 5 ms: "
                f"{sum(lag > 0.005 for lag in lags)}")


async def measure(seconds: float) -> int:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with simulated([ah]) as line:
        config: dict[str, Any] = {"gateway_id": "lag", "buses": [{
            "name": "a", "port": line.path, "baudrate": 115200, "protocol": "native",
            "sensors": [{"name": "s", "series": "AH", "poll_hz": 0}]}]}
        async with running(config):
            await asyncio.sleep(seconds)
        return line.bus.stats.overlaps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    timings = Timings()
    timings.install()
    overlaps = asyncio.run(measure(args.seconds))
    print(timings.report())
    print(f"overlaps seen by the simulator: {overlaps}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
