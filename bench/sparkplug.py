"""Sparkplug B against the plain topics: the gateway's CPU per sample, and whether
every message arrives, at a set sample rate.

The gateway publishes to a real mosquitto (started here) for 4 AH sensors whose
readings are put into its cache at the rate asked (as the bus masters would, without
their serial lines). A subscriber in a process of its own counts what arrives. Three
configurations in the same run: the plain topics alone (the reference), Sparkplug B
alone, and both. Printed: samples/s, messages/s expected and delivered, and the
gateway's CPU (cores, and ms per sample).

Run: ``.venv/bin/python bench/sparkplug.py [--seconds 5]``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import multiprocessing
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from common import FED_SENSORS, fed, fed_config, free_port
from paho.mqtt.enums import CallbackAPIVersion

SENSORS = FED_SENSORS


def _count(port: int, topic: str, seconds: float, out: multiprocessing.Queue[int]) -> None:
    count = [0]
    client = paho.Client(CallbackAPIVersion.VERSION2)
    client.on_message = lambda *_: count.__setitem__(0, count[0] + 1)
    client.connect("127.0.0.1", port)
    client.subscribe(topic, qos=0)
    client.loop_start()
    time.sleep(1.0)  # the births and retained messages are in
    count[0] = 0
    time.sleep(seconds)
    client.loop_stop()
    out.put(count[0])


async def run_case(port: int, mode: str, rate: float, seconds: float) -> tuple[int, float]:
    mqtt: dict[str, Any] = {"url": f"mqtt://127.0.0.1:{port}", "retain": False}
    if mode != "plain":
        mqtt["sparkplug"] = {"group_id": "bench", "plain_topics": mode == "both"}
    topic = "spBv1.0/bench/DDATA/#" if mode == "sparkplug" else "imu/bench/+/state"
    started = time.monotonic()
    delivered, cores, *_ = await fed(fed_config(mqtt=mqtt), rate, seconds,
                                    lambda gw: time.monotonic() - started > 1.0,  # connected
                                    _count, (port, topic), settle=1.0)
    return delivered, cores


def main() -> None:
    logging.getLogger("imu_gateway").setLevel(logging.ERROR)  # the port it cannot open
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = free_port()
    with tempfile.TemporaryDirectory() as folder:
        conf = Path(folder) / "mosquitto.conf"
        conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n"
                        "max_queued_messages 100000\n")
        broker = subprocess.Popen([mosquitto, "-c", str(conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            time.sleep(0.5)
            print(f"MQTT to mosquitto, {SENSORS} AH sensors, {args.seconds:g} s per case")
            print(f"{'samples/s':>9} {'mode':>9} {'expected/s':>10} {'delivered/s':>11} "
                  f"{'ratio':>5} {'gw cores':>8} {'gw ms/sample':>12}")
            for rate in (100, 500, 2000):
                for mode in ("plain", "sparkplug", "both"):
                    delivered, cores = asyncio.run(run_case(port, mode, rate, args.seconds))
                    got = delivered / args.seconds
                    print(f"{rate:>9} {mode:>9} {rate:>10} {got:>11.0f} {got / rate:>5.2f} "
                          f"{cores:>8.3f} {1000 * cores / rate:>12.3f}", flush=True)
        finally:
            broker.terminate()
            broker.wait(10)


if __name__ == "__main__":
    main()
