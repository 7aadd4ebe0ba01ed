"""Modbus TCP: the gateway against a bare pymodbus server, in the same run.

Three processes besides this one: the sensor simulator, the gateway (``imu-gateway
run``) polling one AH sensor at 115200 baud, and a bare pymodbus 3.16 server with a
static datastore (the ceiling: it does nothing but answer).  This process is the load:
1, 10 and 100 concurrent clients, each a raw asyncio connection reading the
32-register float block (FC03, 100-131) in a loop, the same client code for both
servers.  Printed: reads/s, p50/p99 latency, gateway/bare, and the serial bus's
transaction rate (from the sensor's own sequence register) with 0 and 100 clients.

Run: ``.venv/bin/python bench/modbus_tcp.py [--seconds 5]``
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import struct
import sys
import time

from common import free_port, processes

BARE_SERVER = """
import asyncio, sys
from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
from pymodbus.server import StartAsyncTcpServer
block = ModbusSequentialDataBlock(1, list(range(300)))  # 3.16 stores address - 1
context = ModbusServerContext(devices=ModbusDeviceContext(hr=block, ir=block), single=True)
asyncio.run(StartAsyncTcpServer(context=context, address=("127.0.0.1", int(sys.argv[1]))))
"""

READ = struct.Struct(">HHHBBHH")


async def wait_for_port(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)


async def read_registers(port: int, unit: int, start: int, count: int) -> list[int]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(READ.pack(1, 0, 6, unit, 3, start, count))
    header = await reader.readexactly(9)
    data = await reader.readexactly(header[8])
    writer.close()
    return list(struct.unpack(f">{count}H", data))


async def client(port: int, unit: int, deadline: float, latencies: list[float]) -> int:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    answer_size = 9 + 64
    done = 0
    transaction = 0
    while (now := time.perf_counter()) < deadline:
        transaction = (transaction + 1) & 0xFFFF
        writer.write(READ.pack(transaction, 0, 6, unit, 3, 100, 32))
        answer = await reader.readexactly(answer_size)
        if answer[7] != 3:
            raise SystemExit(f"exception answer {answer.hex()}")
        latencies.append(time.perf_counter() - now)
        done += 1
    writer.close()
    return done


async def load(port: int, unit: int, clients: int, seconds: float) -> tuple[float, float, float]:
    latencies: list[float] = []
    deadline = time.perf_counter() + seconds
    started = time.perf_counter()
    counts = await asyncio.gather(*(client(port, unit, deadline, latencies)
                                    for _ in range(clients)))
    elapsed = time.perf_counter() - started
    latencies.sort()
    p99 = latencies[int(len(latencies) * 0.99) - 1] if latencies else float("nan")
    return sum(counts) / elapsed, statistics.median(latencies) * 1000, p99 * 1000


async def bus_rate(port: int, seconds: float) -> tuple[float, float]:
    """The serial bus's transactions/s and utilisation over ``seconds``, from the
    gateway's diagnostics unit 255 (transactions: registers 0-1, busy ms: 4-5)."""
    async def sample() -> tuple[int, int, float]:
        regs = await read_registers(port, 255, 0, 6)
        return regs[0] << 16 | regs[1], regs[4] << 16 | regs[5], time.perf_counter()

    n0, busy0, t0 = await sample()
    await asyncio.sleep(seconds)
    n1, busy1, t1 = await sample()
    return (n1 - n0) / (t1 - t0), (busy1 - busy0) / 1000 / (t1 - t0)


async def measure(gateway_port: int, bare_port: int, seconds: float) -> None:
    await wait_for_port(gateway_port)
    await wait_for_port(bare_port)
    await asyncio.sleep(1.0)  # the sensor's first readings
    print(f"{'clients':>7} {'server':>8} {'reads/s':>9} {'p50 ms':>7} {'p99 ms':>7} "
          f"{'gateway/bare':>12}")
    for clients in (1, 10, 100):
        bare = await load(bare_port, 1, clients, seconds)
        gateway = await load(gateway_port, 1, clients, seconds)
        for name, (rate, p50, p99) in (("bare", bare), ("gateway", gateway)):
            ratio = f"{gateway[0] / bare[0]:12.2f}" if name == "gateway" else ""
            print(f"{clients:7} {name:>8} {rate:9.0f} {p50:7.2f} {p99:7.2f} {ratio}", flush=True)
    print("serial bus (poll_hz 0):  transactions/s  utilisation")
    idle = await bus_rate(gateway_port, seconds)
    print(f"  0 clients             {idle[0]:14.1f} {idle[1]:12.3f}", flush=True)
    on_gateway, _ = await asyncio.gather(
        bus_rate(gateway_port, seconds), load(gateway_port, 1, 100, seconds))
    print(f"  100 on the gateway    {on_gateway[0]:14.1f} {on_gateway[1]:12.3f}", flush=True)
    # The same load on the bare server: the machine is as busy, the gateway is not.
    on_bare, _ = await asyncio.gather(
        bus_rate(gateway_port, seconds), load(bare_port, 1, 100, seconds))
    print(f"  100 on the bare server{on_bare[0]:14.1f} {on_bare[1]:12.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    gateway_port, bare_port = free_port(), free_port()
    bare = [sys.executable, "-c", BARE_SERVER, str(bare_port)]
    interfaces = f"modbus:\n  listen: 127.0.0.1:{gateway_port}\n  max_connections: 200"
    with processes("{name: ah, series: AH, address: 0, poll_hz: 0}", interfaces, bare):
        print(f"Modbus TCP, 32-register float block, {args.seconds} s per run, "
              f"{os.cpu_count()} CPUs; load generator: raw asyncio clients in one process")
        asyncio.run(measure(gateway_port, bare_port, args.seconds))


if __name__ == "__main__":
    main()
