"""Read Device Identification (FC 43 / MEI 14) on the Modbus TCP server, against two
independent clients: pymodbus's and Node's ``modbus-serial`` (tests/node).  Plain
sockets check the refusals byte by byte.  Expected values are written out here from
docs/register-map.md, never taken from the server's own table."""

from __future__ import annotations

import asyncio
import json
import shutil
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.pdu.mei_message import ReadDeviceInformationResponse
from support import ROOT
from support.harness import running, until

from imu_gateway import __version__
from imu_gateway.app import Gateway
from imu_gateway.frontends.modbus import ident
from imu_gateway.frontends.modbus.ident import Identity
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

NODE_DIR = ROOT / "tests" / "node"
READING = Motion.from_seed(3).sample(10.0)
MBAP = struct.Struct(">HHHB")
DIAG_UNIT = 255

# docs/register-map.md, "Device identification"
VENDOR = b"Wuxi Bewis Sensing Technology"
EXPECTED = {
    11: {0: VENDOR, 1: b"AH", 2: f"imu-gateway {__version__}".encode(),
         3: b"www.bwsensing.com", 4: b"AH attitude and heading reference",
         5: b"AH over native protocol", 6: b"boom"},
    12: {0: VENDOR, 1: b"VG", 2: f"imu-gateway {__version__}".encode(),
         3: b"www.bwsensing.com", 4: b"VG vertical gyro", 5: b"VG over Modbus RTU",
         6: b"mast"},
    DIAG_UNIT: {0: b"imu-gateway project", 1: b"imu-gateway", 2: __version__.encode(),
                4: b"imu-gateway", 5: b"Modbus TCP gateway", 6: b"ident-test"},
}


def _config(native: str, modbus: str) -> dict[str, Any]:
    def line(name: str, port: str, protocol: str, sensor: dict[str, Any]) -> dict[str, Any]:
        return {"name": name, "port": port, "baudrate": 115200, "protocol": protocol,
                "sensors": [sensor], "timeout_ms": 300}

    return {"gateway_id": "ident-test",
            "buses": [line("a", native, "native",
                           {"name": "boom", "series": "AH", "unit_id": 11}),
                      line("b", modbus, "modbus", {"name": "mast", "series": "VG",
                                                   "address": 1, "unit_id": 12,
                                                   "raw_unit_id": 112})],
            "modbus": {"listen": "127.0.0.1:0"}}


@pytest.fixture
def lines() -> Iterator[tuple[str, str]]:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=115200, source=hold(READING))
    with simulated([ah]) as a, simulated([vg]) as b:
        yield a.path, b.path


def port_of(gateway: Gateway) -> int:
    assert gateway.modbus is not None
    return gateway.modbus.port


async def identify(client: AsyncModbusTcpClient, read_code: int, device_id: int,
                   object_id: int = 0) -> dict[int, bytes]:
    """pymodbus's read of the objects; asserts the conformity level and no more."""
    answer = await client.read_device_information(read_code=read_code, object_id=object_id,
                                                  device_id=device_id)
    assert isinstance(answer, ReadDeviceInformationResponse), answer
    assert answer.conformity == 0x82 and answer.more_follows == 0
    return dict(answer.information)


async def ask(port: int, unit: int, pdu: bytes) -> bytes:
    """One request on a plain socket; the answer PDU."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(MBAP.pack(7, 0, len(pdu) + 1, unit) + pdu)
        tid, _, length, echoed = MBAP.unpack(await reader.readexactly(MBAP.size))
        assert (tid, echoed) == (7, unit)
        return await reader.readexactly(length - 1)
    finally:
        writer.close()


@pytest.mark.anyio
async def test_pymodbus_reads_each_unit_s_identification(lines: tuple[str, str]) -> None:
    async with running(_config(*lines)) as gw:
        client = AsyncModbusTcpClient("127.0.0.1", port=port_of(gw))
        await client.connect()
        try:
            for unit, objects in EXPECTED.items():
                basic = await identify(client, read_code=1, device_id=unit)
                assert basic == {i: objects[i] for i in (0, 1, 2)}
                regular = await identify(client, read_code=2, device_id=unit)
                assert regular == objects
                extended = await identify(client, read_code=3, device_id=unit)
                assert extended == objects  # no extended objects
                one = await identify(client, read_code=4, object_id=5,
                                                           device_id=unit)
                assert one == {5: objects[5]}
                # a stream from object 4 on; from one outside basic, basic from its start
                tail = await identify(client, read_code=2, object_id=4,
                                                            device_id=unit)
                assert tail == {i: v for i, v in objects.items() if i >= 4}
                restart = await identify(client, read_code=1, object_id=5,
                                                               device_id=unit)
                assert restart == basic
            # the raw unit of a sensor is that sensor
            raw = await identify(client, read_code=2, device_id=112)
            assert raw == EXPECTED[12]
        finally:
            client.close()


@pytest.mark.anyio
async def test_refusals_are_the_standard_s_exceptions(lines: tuple[str, str]) -> None:
    async with running(_config(*lines)) as gw:
        port = port_of(gw)
        assert await ask(port, 11, bytes((0x2B, 0x0E, 4, 0x80))) == b"\xab\x02"  # no object
        assert await ask(port, DIAG_UNIT, bytes((0x2B, 0x0E, 4, 3))) == b"\xab\x02"  # no url
        assert await ask(port, 11, bytes((0x2B, 0x0E, 5, 0))) == b"\xab\x03"  # read code
        assert await ask(port, 11, bytes((0x2B, 0x0E, 1))) == b"\xab\x03"  # too short
        assert await ask(port, 11, bytes((0x2B, 0x0D, 1, 0))) == b"\xab\x01"  # not MEI 14
        assert await ask(port, 99, bytes((0x2B, 0x0E, 1, 0))) == b"\xab\x0a"  # no unit
        # and the server goes on serving reads
        assert (await ask(port, 11, bytes((3, 0, 6, 0, 1))))[:2] == b"\x03\x02"


NODE_CLIENT = r"""
const ModbusRTU = require("modbus-serial");
const [port, ...units] = process.argv.slice(2).map(Number);
(async () => {
  const client = new ModbusRTU();
  await client.connectTCP("127.0.0.1", { port });
  client.setTimeout(5000);
  const out = {};
  for (const unit of units) {
    client.setID(unit);
    const answer = await client.readDeviceIdentification(2, 0);
    out[unit] = { conformity: answer.conformityLevel, data: answer.data };
  }
  console.log(JSON.stringify(out));
  client.close(() => {});
})().catch((e) => { console.error(e); process.exit(1); });
"""


@pytest.mark.anyio
async def test_node_modbus_serial_reads_the_identification(lines: tuple[str, str],
                                                          tmp_path: Path) -> None:
    node = shutil.which("node")
    assert node is not None, "node is needed: scripts/bootstrap --test installs it"
    assert (NODE_DIR / "node_modules" / "modbus-serial").is_dir(), \
        "run scripts/bootstrap --test (npm ci in tests/node)"
    script = tmp_path / "ident.js"
    script.write_text(NODE_CLIENT)
    async with running(_config(*lines)) as gw:
        await until(lambda: gw.modbus is not None and gw.modbus.listening)
        proc = await asyncio.create_subprocess_exec(
            node, str(script), str(port_of(gw)), *(str(u) for u in EXPECTED),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={"NODE_PATH": str(NODE_DIR / "node_modules")})
        out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 0, err.decode()
    got = json.loads(out)
    for unit, objects in EXPECTED.items():
        assert got[str(unit)]["conformity"] == 0x82
        assert got[str(unit)]["data"] == {str(i): v.decode() for i, v in objects.items()}


@pytest.mark.parametrize("name_length", [1, 100, 117, 118, 240, 246, 247, 400])
def test_every_answer_fits_a_pdu_and_a_stream_read_ends(name_length: int) -> None:
    """However long the name (a sensor's, or a gateway_id), each answer is at most
    253 bytes, and reading a category object after object comes to its end."""
    for who in (Identity(Series.AH, WireProtocol.MODBUS, "n" * name_length),
                Identity(None, None, "g" * name_length)):
        for code in (1, 2, 3):
            first, seen = 0, 0
            for _ in range(10):
                pdu = ident.answer(bytes((0x2B, 0x0E, code, first)), who)
                assert len(pdu) <= ident.MAX_PDU and pdu[0] == 0x2B, (code, first, len(pdu))
                seen += pdu[6]
                if pdu[4] == 0x00:
                    break
                first = pdu[5]
            else:
                raise AssertionError(f"code {code}: more follows for ever")
            assert seen == sum(1 for i in ident.STREAM_CODES[code] if ident.BY_ID[i].has(who))
        for obj in ident.OBJECTS:
            if obj.has(who):
                assert len(ident.answer(bytes((0x2B, 0x0E, 4, obj.id)), who)) <= ident.MAX_PDU
