"""The ``imu-gateway`` command line.

Every bad input ends in one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import signal
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeAlias

from .. import __version__
from ..bus.timing import RTO_INITIAL
from ..model import Series, WireProtocol
from ..protocol.modbus_rtu import UNIT_IDS
from ..protocol.native import BAUD_CODES
from .decode import decode_all, to_json_line
from .init import InitError

if TYPE_CHECKING:
    from ..config import GatewayConfig
    from ..simulator import PtyBus, SimSensor
    from ..simulator.control import ControlSocket
    from .scan import Found, Progress

EXIT_BAD_INPUT = 2


def _series(text: str) -> Series:
    try:
        return Series[text.upper()]
    except KeyError:
        raise argparse.ArgumentTypeError(
            f"series must be one of {', '.join(s.name for s in Series)}, not {text!r}"
        ) from None


def _protocol(text: str) -> WireProtocol:
    try:
        return WireProtocol[text.upper()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"protocol must be native or modbus, not {text!r}") \
            from None


def _baud(text: str) -> int:
    if not text.isdigit() or int(text) not in BAUD_CODES.values():
        raise argparse.ArgumentTypeError(
            f"baud rate must be one of {sorted(BAUD_CODES.values())}, not {text!r}"
        )
    return int(text)


def _address(text: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 255:
        raise argparse.ArgumentTypeError(f"address must be 0-255, not {text!r}")
    return int(text)


def _register(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        value = -1
    if not 0 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"register must be 0-65535 (0x.. allowed), not {text!r}")
    return value


def _float_in(low: float, high: float, what: str) -> Callable[[str], float]:
    """An argparse type: a float within [low, high], else one clear error naming ``what``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not low <= value <= high:  # NaN fails this too
            raise argparse.ArgumentTypeError(f"must be {what}, not {text!r}")
        return value

    return parse


_probability = _float_in(0.0, 1.0, "a probability 0-1")
_non_negative = _float_in(0.0, math.inf, "a number >= 0")


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a TCP port is 0-65535, not {text!r}")
    return value


def _sensor_spec(text: str) -> tuple[WireProtocol, Series, int | None, int]:
    """``PROTOCOL:SERIES[:ADDRESS[:BAUD]]``, e.g. ``modbus:VG:2:19200``."""
    parts = text.split(":")
    if not 2 <= len(parts) <= 4:
        raise argparse.ArgumentTypeError(
            f"sensor must be PROTOCOL:SERIES[:ADDRESS[:BAUD]], not {text!r}"
        )
    protocol, series = _protocol(parts[0]), _series(parts[1])
    address = _address(parts[2]) if len(parts) > 2 and parts[2] else None
    baud = _baud(parts[3]) if len(parts) > 3 else 9600
    return protocol, series, address, baud


#: argparse's subcommand collection (what ``add_subparsers`` returns; its class is
#: private)
Subcommands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="imu-gateway",
        description="One owner per serial bus of IMU/VG/AH/MINS attitude sensors.",
    )
    parser.add_argument("--version", action="version", version=f"imu-gateway {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _decode_parser(commands)
    _run_parser(commands)
    _demo_parser(commands)
    _scan_parser(commands)
    _simulate_parser(commands)
    _simulate_control_parser(commands)
    _check_config_parser(commands)
    _hash_password_parser(commands)
    _init_parser(commands)
    return parser


def _decode_parser(commands: Subcommands) -> None:
    decode = commands.add_parser(
        "decode",
        help="decode captured frames to JSON lines",
        description="Decode captured frames (hex, spaces allowed) to one JSON object per line. "
        "A data answer prints as the reading JSON's value groups, any other frame as "
        "its command name and fields. A bad frame exits 2 with the reason on stderr.",
    )
    decode.add_argument("frames", nargs="+", metavar="FRAME")
    decode.add_argument("--protocol", type=_protocol, help="native or modbus (default: guess)")
    decode.add_argument("--series", type=_series, help="IMU, VG, AH or MINS")
    decode.add_argument(
        "--start", type=_register,
        help="first register of the read a Modbus answer answers (when its request "
        "is not given before it)",
    )


def _run_parser(commands: Subcommands) -> None:
    run = commands.add_parser(
        "run",
        help="run the gateway",
        description="Run the gateway: own the buses of the config, serve the interfaces it "
        "turns on. Stops cleanly on SIGINT or SIGTERM.",
    )
    run.add_argument("-c", "--config", required=True, metavar="FILE", help="the YAML config")
    run.add_argument("--log-level", default="info",
                     choices=["debug", "info", "warning", "error"], help="default: info")
    run.add_argument("--trace", action="append", default=[], metavar="BUS",
                     help="log every exchange of this bus (repeatable; see the bus's "
                     "`trace` setting)")
    run.add_argument("--stats-interval", type=_non_negative, default=0.0, metavar="SECONDS",
                     help="log each bus's rate and utilisation this often (0: never)")


def _demo_parser(commands: Subcommands) -> None:
    demo = commands.add_parser(
        "demo",
        help="the gateway on simulated sensors (no hardware)",
        description="The whole gateway on built-in simulated sensors: a native AH and a "
        "streaming MINS on one simulated line, a Modbus VG on another. Modbus TCP, REST, "
        "the dashboard, OPC UA and MQTT (when a broker is reachable) are up; ready command lines "
        "are printed. Stop with Ctrl-C.",
    )
    demo.add_argument("--modbus-port", type=_port, default=5020, help="default 5020")
    demo.add_argument("--http-port", type=_port, default=8080, help="default 8080")
    demo.add_argument("--opcua-port", type=_port, default=4840, help="default 4840")
    demo.add_argument("--mqtt", default="mqtt://localhost:1883", metavar="URL",
                      help="the broker (default mqtt://localhost:1883; retried quietly "
                      "while it is not there)")
    demo.add_argument("--listen-host", default="127.0.0.1", metavar="HOST",
                      help="the address Modbus TCP and HTTP listen on (default 127.0.0.1; "
                      "0.0.0.0 to be reached from other machines)")
    demo.add_argument("--log-level", default="warning",
                      choices=["debug", "info", "warning", "error"], help="default: warning")


def _scan_parser(commands: Subcommands) -> None:
    scan = commands.add_parser(
        "scan",
        help="find the sensors on a port",
        description="Find the sensors on a port: both protocols, every baud rate, every "
        "address. Only reads are sent. The gateway must not be running on the port. "
        "Progress, with an estimate of the time left, goes to stderr; so does, when "
        "something was found, the narrower scan that would have been enough.",
    )

    def count(text: str) -> int:
        if not text.isdigit() or int(text) < 1:
            raise argparse.ArgumentTypeError(f"must be a whole number >= 1, not {text!r}")
        return int(text)

    scan.add_argument("--port", required=True, help="a device path or a pyserial URL")
    scan.add_argument("--protocol", type=_protocol, action="append",
                      help="only this protocol (repeatable; default: both)")
    scan.add_argument("--baud", type=_baud, action="append",
                      help="only this baud rate (repeatable; default: all eight)")
    scan.add_argument("--address", type=_address, action="append",
                      help="only this address (repeatable; default: native 0-255, Modbus "
                      "1-247)")
    scan.add_argument("--all-addresses", action="store_true",
                      help="Modbus units 248-255 too, which Modbus reserves (the config "
                      "refuses them) but a sensor can be set to. Never unit 0: it is "
                      "broadcast, which a sensor carries out without answering, so a read "
                      "sent to it finds nothing")
    scan.add_argument("--stop-after", type=count, metavar="N",
                      help="stop once N sensors are found")
    scan.add_argument("--margin-ms", type=_non_negative, default=RTO_INITIAL * 1000,
                      help="wait this long beyond the wire time for an answer (default "
                      f"{RTO_INITIAL * 1000:g}: a slow sensor behind a USB adapter, the "
                      "gateway's own first timeout)")


def _simulate_parser(commands: Subcommands) -> None:
    sim = commands.add_parser(
        "simulate",
        help="simulated sensors on a pseudo-terminal",
        description="Simulated sensors on one pseudo-terminal. The first stdout line is "
        "'PTY <path>'. Wire time is honoured. Stop with Ctrl-C.",
    )
    sim.add_argument("--protocol", type=_protocol, help="native or modbus")
    sim.add_argument("--series", type=_series, help="IMU, VG, AH or MINS")
    sim.add_argument("--address", type=_address,
                     help="bus address (default 0 native, 1 modbus)")
    sim.add_argument("--baud", type=_baud, default=9600, help="the sensor's baud rate")
    sim.add_argument(
        "--sensor", type=_sensor_spec, action="append", default=[],
        metavar="PROTOCOL:SERIES[:ADDRESS[:BAUD]]",
        help="another sensor on the same line (repeatable)",
    )
    sim.add_argument("--answer-delay-ms", type=_non_negative, default=2.0,
                     help="the sensors' turnaround before answering (default 2; 0 answers "
                     "at once); a Modbus sensor waits out RTU's 3.5-character silence first "
                     "unless --below-gap")
    sim.add_argument("--below-gap", action="store_true",
                     help="Modbus sensors answer --answer-delay-ms after the request's last "
                     "byte, inside RTU's 3.5-character silence, as many real sensors do")
    sim.add_argument("--jitter-ms", type=_non_negative, default=0.0,
                     help="each answer's delay is --answer-delay-ms plus a uniform random "
                     "0..jitter ms (seeded by --seed)")
    sim.add_argument("--save-ms", type=_non_negative, default=4000.0,
                     help="save's deaf period (default 4000; the document says 3-5 s)")
    sim.add_argument("--drop", type=_probability, default=0.0,
                     help="probability that an answer is dropped")
    sim.add_argument("--corrupt", type=_probability, default=0.0,
                     help="probability that a frame has a flipped bit")
    sim.add_argument("--noise", type=_non_negative, default=0.0,
                     help="bursts of line noise per second, while the line is idle")
    sim.add_argument("--seed", type=int, default=0, help="seed of motion and faults")
    sim.add_argument("--link", help="also make the pty reachable at this path (a symlink); "
                     "with --replay of several lines, PATH.<bus> for each")
    sim.add_argument("--control", metavar="PATH", help="take commands (lean ADDRESS PITCH "
                     "ROLL, lean ADDRESS off) on a Unix socket at PATH: see simulate-control")
    sim.add_argument("--replay", metavar="CAPTURE.zip",
                     help="play a capture's lines back, one pty each (docs/simulator.md, "
                     "Replay); the sensor options do not apply")
    sim.add_argument("-v", "--verbose", action="store_true", help="log every frame to stderr")


def _simulate_control_parser(commands: Subcommands) -> None:
    control = commands.add_parser(
        "simulate-control",
        help="send a command to a running simulator",
        description="Send one command to the control socket of 'imu-gateway simulate "
        "--control PATH' and print its answer: 'ok' (exit 0), or the error (exit 2). "
        "Commands: lean ADDRESS PITCH ROLL (degrees; ADDRESS may be native:N or modbus:N), "
        "lean ADDRESS off, turn ADDRESS HEADING [RATE] (degrees, deg/s), turn ADDRESS off.",
    )
    control.add_argument("path", metavar="PATH", help="the simulator's --control socket")
    control.add_argument("words", nargs="+", metavar="WORD", help="the command, e.g. lean 1 7.5 0")


def _check_config_parser(commands: Subcommands) -> None:
    check = commands.add_parser(
        "check-config",
        help="validate a config file",
        description="Validate a config file: exit 0 with a one-line summary, or print each "
        "problem with its YAML path on stderr and exit 2.",
    )
    check.add_argument("-c", "--config", required=True, metavar="FILE",
                       help="the YAML config file")


def _hash_password_parser(commands: Subcommands) -> None:
    commands.add_parser(
        "hash-password",
        help="print a password's hash for http.users",
        description="Read a password (asked twice on a terminal; else the first line of "
        "stdin) and print its scrypt hash, for `password:` of a user in http.users "
        "(docs/rest.md, \"Roles\").",
    )


def cmd_hash_password(args: argparse.Namespace) -> int:
    import getpass

    from ..passwords import hash_password

    if sys.stdin.isatty():
        password = getpass.getpass("password: ")
        if getpass.getpass("again: ") != password:
            print("imu-gateway hash-password: the two passwords differ", file=sys.stderr)
            return EXIT_BAD_INPUT
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    if not password:
        print("imu-gateway hash-password: the password is empty", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(hash_password(password))
    return 0


def _init_parser(commands: Subcommands) -> None:
    init = commands.add_parser(
        "init",
        help="write a commented starter config",
        description="Write a commented starter config: from a scan of a port (--scan), "
        "from questions on stdin (each with a default; --yes takes them all), or a copy "
        "of a shipped example (--example). What it writes passes check-config. An "
        "existing file is never overwritten without --force.",
    )
    source = init.add_mutually_exclusive_group()
    source.add_argument("--scan", metavar="PORT", help="scan this port (as 'imu-gateway "
                        "scan' does; the gateway must not be running on it)")
    source.add_argument("--example", metavar="NAME",
                        help="copy a shipped example: single-native, mixed-bus, "
                        "modbus-rtu-only")
    source.add_argument("--yes", action="store_true",
                        help="take every question's default without asking")
    init.add_argument("-o", "--output", default="gateway.yaml", metavar="FILE",
                      help="the file to write (default gateway.yaml)")
    init.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    init.add_argument("--gateway-id", default="gateway-1", help="with --scan (default "
                      "gateway-1)")
    init.add_argument("--protocol", type=_protocol, action="append",
                      help="with --scan: only this protocol (repeatable; default both)")
    init.add_argument("--baud", type=_baud, action="append",
                      help="with --scan: only this baud rate (repeatable; default all)")


def cmd_decode(args: argparse.Namespace) -> int:
    status = 0
    for index, item in enumerate(decode_all(args.frames, args.protocol, args.series, args.start)):
        if item.result is not None:
            print(to_json_line(item.result), flush=True)
        else:
            print(f"imu-gateway decode: frame {index + 1} ({item.text.strip()}): {item.error}",
                  file=sys.stderr)
            status = EXIT_BAD_INPUT
    return status


def _load_or_report(path: str) -> GatewayConfig | None:
    from ..config import load_config
    from ..errors import ConfigError

    try:
        return load_config(path)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return None


def cmd_run(args: argparse.Namespace) -> int:
    from ..app import run_until_signalled
    from ..config.loading import ConfigSource
    from ..errors import StartupError

    config = _load_or_report(args.config)
    if config is None:
        return EXIT_BAD_INPUT
    names = [b.name for b in config.buses]
    unknown = [name for name in args.trace if name not in names]
    if unknown:
        print(f"imu-gateway run: error: --trace {unknown[0]}: no such bus (the buses: "
              f"{', '.join(names)})", file=sys.stderr)
        return EXIT_BAD_INPUT
    config = config.model_copy(update={"buses": [
        b.model_copy(update={"trace": True}) if b.name in args.trace else b
        for b in config.buses]})
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    try:
        asyncio.run(run_until_signalled(config, args.stats_interval,
                                        source=ConfigSource.read(args.config)))
    except StartupError as exc:
        print(f"imu-gateway run: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from ..errors import ConfigError, StartupError
    from .demo import DemoOptions, run_demo

    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    try:
        run_demo(DemoOptions(args.modbus_port, args.http_port, args.mqtt, args.listen_host,
                             args.opcua_port))
    except StartupError as exc:
        print(f"imu-gateway demo: error: {exc} (choose another port with --modbus-port, "
              "--http-port or --opcua-port)", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ConfigError as exc:
        print(f"imu-gateway demo: error: {'; '.join(exc.problems)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0


def cmd_scan(args: argparse.Namespace) -> int:
    import serial

    from .scan import (
        BAUD_ORDER,
        Throttle,
        modbus_units,
        next_time,
        port_problem,
        scan,
    )

    protocols = args.protocol or list(WireProtocol)
    if args.address and WireProtocol.MODBUS in protocols:
        # Said rather than silently skipped: the engineer asked for these addresses.
        skipped = sorted(set(args.address) - set(modbus_units(args.address, args.all_addresses)))
        if skipped:
            print(f"imu-gateway scan: note: Modbus does not ask {', '.join(map(str, skipped))} "
                  "(0 is broadcast, never answered; 248-255 need --all-addresses)",
                  file=sys.stderr)

    def show(progress: Progress) -> None:
        print(progress.line(), file=sys.stderr, flush=True)

    found: list[Found] = []
    sensors = scan(args.port, protocols, args.baud or BAUD_ORDER, args.address,
                   args.margin_ms / 1000, Throttle(show), args.all_addresses)
    try:
        for sensor in sensors:
            print(sensor.line(), flush=True)
            found.append(sensor)
            if len(found) == args.stop_after:
                break
    except serial.SerialException as exc:
        print(f"imu-gateway scan: error: {port_problem(args.port, exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("imu-gateway scan: interrupted", file=sys.stderr)
        return 130
    finally:
        sensors.close()  # frees the port at once, also when --stop-after ends the scan
    stopped = f" (stopped: --stop-after {args.stop_after})" if len(found) == args.stop_after \
        else ""
    print(f"{len(found)} sensor{'s' if len(found) != 1 else ''} found{stopped}", file=sys.stderr)
    if found:
        margin = None if args.margin_ms == RTO_INITIAL * 1000 else args.margin_ms
        print(next_time(args.port, found, margin), file=sys.stderr)
    return 0 if found else 1


def cmd_replay(args: argparse.Namespace) -> int:
    """``simulate --replay``: a pty per line of the capture, ``PTY <path> <bus>`` each."""
    from ..simulator.replay import Replay, load

    try:
        replay = Replay(load(args.replay), link=args.link)
        paths = replay.open()
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        print(f"imu-gateway simulate: error: --replay {args.replay}: {reason}",
              file=sys.stderr)
        return EXIT_BAD_INPUT

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        for bus, path in paths.items():
            print(f"PTY {path} {bus}", flush=True)
        await replay.serve(stop)

    try:
        asyncio.run(main())
    finally:
        print(f"simulate: replay stopped: {json.dumps(replay.summary())}", file=sys.stderr,
              flush=True)
        replay.close()
    return 0


def cmd_simulate(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    if args.replay:
        return cmd_replay(args)
    from ..simulator import Faults, PtyBus, make_sensor
    from ..simulator.motion import Motion

    specs = list(args.sensor)
    if args.protocol or args.series:
        if not (args.protocol and args.series):
            parser.error("simulate: --protocol and --series go together")
        specs.insert(0, (args.protocol, args.series, args.address, args.baud))
    if not specs:
        parser.error("simulate: give --protocol and --series, or --sensor")
    if not math.isfinite(args.jitter_ms):  # _non_negative lets inf through
        parser.error("simulate: --jitter-ms must be finite")
    sensors = [
        make_sensor(
            protocol, series, address, baud,
            source=Motion.from_seed(args.seed + i),
            answer_delay=args.answer_delay_ms / 1000,
            keep_gap=not args.below_gap,
            jitter=args.jitter_ms / 1000,
            save_duration=args.save_ms / 1000,
            faults=Faults(drop_rate=args.drop, corrupt_rate=args.corrupt),
            seed=args.seed + i,
        )
        for i, (protocol, series, address, baud) in enumerate(specs)
    ]
    for sensor in sensors:
        if sensor.protocol is WireProtocol.MODBUS and sensor.address not in UNIT_IDS:
            parser.error(f"simulate: a Modbus address is 1-247, not {sensor.address}")
    if len({(s.protocol, s.address) for s in sensors}) < len(sensors):
        parser.error("simulate: two sensors of one protocol share an address")
    bus = PtyBus(sensors, noise_rate=args.noise, seed=args.seed, link=args.link,
                 verbose=args.verbose)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        try:
            path = bus.open()
        except OSError as exc:
            print(f"imu-gateway simulate: error: --link {args.link}: {exc.strerror or exc}",
                  file=sys.stderr)
            raise SystemExit(EXIT_BAD_INPUT) from None
        control = await _open_control(args.control, sensors, bus)  # before PTY: ready then
        print(f"PTY {path}", flush=True)
        for sensor in sensors:
            print(f"sensor {sensor.name} at {sensor.baud} baud", file=sys.stderr, flush=True)
        try:
            await bus.serve(stop)
        finally:
            if control is not None:
                control.close()
        # What the line saw, for whoever drove it (a benchmark, a test, a curious user).
        stats = bus.stats
        summary = {"requests_bytes": stats.requests_bytes, "answer_frames": stats.answer_frames,
                   "overlaps": stats.overlaps, "collisions": stats.collisions,
                   "holds": stats.holds, "held_s": round(stats.held_s, 3),
                   "lags": stats.lags, "lagged_s": round(stats.lagged_s, 3),
                   "overlaps_after_hold": stats.overlaps_after_hold,
                   "collisions_after_hold": stats.collisions_after_hold,
                   "writes_heard": {s.name: dict(s.writes_heard) for s in sensors},
                   "incidents": stats.incidents}
        print(f"simulate: stopped: {json.dumps(summary)}", file=sys.stderr, flush=True)

    asyncio.run(main())
    return 0


async def _open_control(path: str | None, sensors: Sequence[SimSensor],
                        bus: PtyBus) -> ControlSocket | None:
    from ..simulator.control import open_control

    if path is None:
        return None
    try:
        return await open_control(path, sensors)
    except OSError as exc:
        bus.close()
        print(f"imu-gateway simulate: error: --control {path}: {exc.strerror or exc}",
              file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT) from None


def cmd_simulate_control(args: argparse.Namespace) -> int:
    from ..simulator.control import OK, send

    try:
        answer = send(args.path, " ".join(args.words))
    except OSError as exc:
        print(f"imu-gateway simulate-control: error: {args.path}: {exc.strerror or exc} (is "
              f"'imu-gateway simulate --control {args.path}' running?)", file=sys.stderr)
        return EXIT_BAD_INPUT
    if answer != OK:
        print(f"imu-gateway simulate-control: {answer or 'error: no answer'}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(answer)
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    from ..capacity import line_loads

    config = _load_or_report(args.config)
    if config is None:
        return EXIT_BAD_INPUT
    print(f"config OK: {config.summary()}")
    for line in _sensor_lines(config):
        print(line)
    for warning in _written_warnings(args.config):
        print(f"warning: {warning}")
    for load in line_loads(config.buses):
        print(load.describe())
        for warning in load.warnings():
            print(f"warning: {warning}")
    for bus in config.buses:
        # Not an error: the adapter may be unplugged now, and the gateway waits for it.
        if bus.port.startswith("/") and not os.path.exists(bus.port):
            print(f"warning: bus {bus.name}: the port {bus.port} does not exist now (an "
                  "adapter unplugged? a udev name not set up?); the gateway keeps trying "
                  "to open it")
    return 0


def _ask(question: str, default: str) -> str:
    """One question on stdout, its answer from stdin; at the end of stdin, the default."""
    try:
        return input(f"{question} [{default}]: ")
    except EOFError:
        print()
        return default


def _scanned(args: argparse.Namespace) -> list[Found]:
    import serial

    from .scan import BAUD_ORDER, Throttle, port_problem, scan

    def show(progress: Progress) -> None:
        print(progress.line(), file=sys.stderr, flush=True)

    sensors = scan(args.scan, args.protocol or list(WireProtocol), args.baud or BAUD_ORDER,
                   progress=Throttle(show))
    try:
        return list(sensors)
    except serial.SerialException as exc:
        raise InitError(f"--scan: {port_problem(args.scan, exc)}") from None
    finally:
        sensors.close()


def cmd_init(args: argparse.Namespace) -> int:
    from .init import example, from_questions, from_scan, render, write

    try:
        if args.example:
            text = example(args.example)
        elif args.scan:
            text = render(from_scan(args.scan, _scanned(args), args.gateway_id))
        else:
            text = render(from_questions((lambda q, d: "") if args.yes else _ask))
        write(args.output, text, args.force)
    except InitError as exc:
        print(f"imu-gateway init: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"wrote {args.output}; check it after each edit: imu-gateway check-config -c "
          f"{args.output}")
    return 0


def _sensor_lines(config: GatewayConfig) -> list[str]:
    """Each sensor's two numbers side by side: the address it is polled at on its bus,
    and the unit a Modbus TCP client asks for it (they are easily confused)."""
    lines = []
    for bus in config.buses:
        for s in bus.sensors:
            raw = f", raw unit {s.raw_unit_id}" if s.raw_unit_id is not None else ""
            lines.append(f"sensor {s.name} ({s.series.name}) on {bus.name}: "
                         f"{bus.protocol.name.lower()} address {s.address}, "
                         f"Modbus TCP unit {s.unit_id}{raw}")
    return lines


def _written_warnings(path: str) -> list[str]:
    """The warnings about what the file says, not what it means once defaults are
    filled in (a Modbus RTU sensor's unit_id without an address)."""
    import yaml

    from ..config.checks import address_warnings

    with open(path, encoding="utf-8-sig") as file:  # load_config read it a moment ago
        return address_warnings(yaml.safe_load(file))


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "simulate":
        return cmd_simulate(args, parser)
    handlers: dict[str, Callable[[argparse.Namespace], int]] = {
        "decode": cmd_decode, "check-config": cmd_check_config, "run": cmd_run,
        "scan": cmd_scan, "demo": cmd_demo, "simulate-control": cmd_simulate_control,
        "hash-password": cmd_hash_password,
        "init": cmd_init,
    }
    return handlers[args.command](args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
