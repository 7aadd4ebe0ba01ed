"""The gateway process: one bus master per bus, the cache between them and the front
ends, and the lifecycle (the gateway, not a web server, owns signals and shutdown).

Only this module imports everything, and a front end only when the config turns it
on: asyncua, FastAPI with uvicorn, paho and protobuf are most of the start-up time
and a good part of the memory, which a bus-only gateway on a small box does without
(docs/deployment.md, "Small boxes"; ``tests/test_lean_start.py`` holds it).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from .alarms import AlarmCounts, AlarmEvent, Alarms, AlarmState, Transition
from .bus.runner import BusThread
from .cache import Cache, EventKind, Snapshot, Status
from .capacity import line_loads
from .commands import CATALOGUE, CommandResult, validate
from .config import (
    BusConfig,
    GatewayConfig,
    HttpConfig,
    ModbusConfig,
    MqttConfig,
    OpcUaConfig,
    SensorConfig,
    config_from_dict,
)
from .config.loading import ConfigSource
from .derived import values_of
from .errors import ErrorKind, RequestFailed, StartupError, unknown_sensor
from .history import History
from .journal import JournalFile
from .reload import Reloader
from .scanning import ScanJob, ScanRequest, same_port
from .stats import BusStats, FrontendCounts, SensorStats, Trace
from .supervise import Frontend, Supervisor

if TYPE_CHECKING:  # the front ends' modules are imported when configured (below)
    from .bus.frames import Frame
    from .capture import Captures
    from .frontends.modbus.server import ModbusTcpServer
    from .frontends.mqtt.client import MqttClient
    from .frontends.opcua.server import OpcUaServer
    from .frontends.rest import HttpServer
    from .frontends.sparkplug.client import SparkplugClient

log = logging.getLogger("imu_gateway")

STALENESS_TICK = 0.1  # seconds between checks that turn "too old" into status events
SHUTDOWN_GRACE = 10.0  # seconds the bus masters get to finish the exchange in flight
# A bus thread woken by its serial port waits for the GIL until the thread holding it
# (busy with front-end clients) lets go: by default up to 5 ms, longer than a whole
# exchange at 115200 baud.  A shorter interval keeps the line's timing (see
# docs/benchmarks.md for the measurement).
GIL_SWITCH_INTERVAL = 0.0005


class _GatewayAlarms:
    """The gateway's alarms (docs/alarms.md): evaluated here on each sample whichever
    front ends are on, published as the cache's ``ALARM`` events, journalled, and
    acknowledged through the front ends (``GatewayLike``'s alarm methods)."""

    cache: Cache
    sensors: dict[str, SensorConfig]
    captures: Captures | None

    def _alarms_setup(self, config: GatewayConfig) -> None:
        """Every alarm, evaluated here on each sample whichever front ends are on (they
        hear the transitions as the cache's ``ALARM`` events), and the journal's file,
        whose last transitions give the alarms the states they had."""
        self.journal_file = JournalFile(config.alarm_journal) if config.alarm_journal else None
        self.alarms = Alarms([a.row(s.name) for _, s in config.iter_sensors() for a in s.alarms],
                             self.sensors, self.journal_file.read() if self.journal_file else ())
        self._evaluating = True  # off once stopping: a sensor going then is no alarm
        self.cache.subscribe(self._on_sample, prompt=False)  # (each sample's own time)

    def _on_sample(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING and self._evaluating and snap.timestamp is not None:
            # when it was received: samples may come in a burst (``Cache.subscribe``)
            at = time.monotonic() - (snap.age_ms or 0.0) / 1000
            for change in self.alarms.sample(snap.name, values_of(snap), at,
                                             snap.timestamp.timestamp()):
                self._publish(change)

    def _check_communication(self) -> None:
        """The communication alarms, at each staleness tick.  A sensor its bus has not
        tried yet is no alarm: at start every sensor is "offline" until then."""
        at, wall = time.monotonic(), time.time()
        for name in self.sensors:
            if self.cache.reached(name):
                ok = self.cache.snapshot(name).status is Status.OK
                change = self.alarms.communication(name, ok, at, wall)
                if change is not None:
                    self._publish(change)

    def _publish(self, change: Transition) -> None:
        if self.journal_file is not None:
            self.journal_file.append(change)
        state = self.alarms.evaluator(change.sensor, change.alarm).snapshot()
        self.cache.publish_alarm(AlarmEvent(change, state))
        if change.to_state.active and not change.from_state.active and \
                self.captures is not None:  # (``capture.on_alarms`` decides)
            self.captures.alarm_active(change.sensor, change.alarm, change.at)

    def alarm_states(self) -> list[AlarmState]:
        return self.alarms.states()

    def alarm_journal(self, since: float | None = None) -> list[Transition]:
        return self.alarms.since(since)

    def acknowledge(self, sensor: str, alarm: str, who: str) -> AlarmState:
        change = self.alarms.acknowledge(sensor, alarm, who, time.time())
        self._publish(change)
        return self.alarms.evaluator(sensor, alarm).snapshot()

    def alarm_counts(self) -> AlarmCounts:
        file = self.journal_file
        return AlarmCounts(dict(self.alarms.transitions), file.written if file else 0,
                           file.errors if file else 0)



class Gateway(_GatewayAlarms):
    """The running gateway as the front ends see it: the cache, and commands."""

    def __init__(self, config: GatewayConfig, source: ConfigSource | None = None) -> None:
        self.config = config
        self.cache = Cache([(s.name, s.stale_after_ms) for _, s in config.iter_sensors()])
        self.buses = BusThread(list(config.buses), self.cache)
        self.hand_over_within(config.hand_over_ms)
        self.runners = self.buses.runners
        self.masters = {name: runner.master for name, runner in self.runners.items()}
        self._runner_of = {s.name: self.runners[b.name] for b, s in config.iter_sensors()}
        self.sensors: dict[str, SensorConfig] = {s.name: s for _, s in config.iter_sensors()}
        # One history for every front end (REST's trends, OPC UA's HistoryRead): its
        # memory is fixed per sensor.  Subscribed first, so it has a reading before any
        # front end shows it.
        self.history = History(self)
        self.cache.subscribe(self.history.on_cache_event, prompt=False)
        self._alarms_setup(config)
        # Event capture: every sample into its ring, every frame into its line's ring
        self.captures = _captures(self) if config.capture else None
        self.modbus = _modbus_server(self, config.modbus) if config.modbus else None
        self.mqtt, self.sparkplug = self._mqtt_clients(config.mqtt)
        self.http = _http_server(self, config.http) if config.http else None
        self.opcua = _opcua_server(self, config.opcua) if config.opcua else None
        # the supervised front ends
        self.frontends: list[Frontend] = [
            f for f in (self.modbus, self.http, self.opcua, self.mqtt, self.sparkplug) if f]
        self.supervisor = Supervisor()
        self._watchers: dict[str, asyncio.Task[None]] = {}
        self._running = False  # between the start of the buses and the front ends' stop
        self.source = source  # the file and its unexpanded text (a reload, GET and PUT)
        self.reloader = Reloader(self)
        self.started = time.monotonic()

    def _mqtt_clients(self, config: MqttConfig | None
                      ) -> tuple[MqttClient | None, SparkplugClient | None]:
        sparkplug = config.sparkplug if config else None
        plain = _mqtt_client(self, config) \
            if config and (sparkplug is None or sparkplug.plain_topics) else None
        return plain, _sparkplug_client(self, config) if config and sparkplug else None

    # ------------------------------------------------------------ a reload (reload.py)

    def adopt(self, config: GatewayConfig) -> None:
        """The new config's sensors, in the cache, the history and the alarms (the
        buses that run them are stopped or started by the reloader)."""
        old_alarms = [a for _, s in self.config.iter_sensors() for a in (s.name, s.alarms)]
        self.config = config
        self.sensors = {s.name: s for _, s in config.iter_sensors()}
        self.cache.set_sensors([(s.name, s.stale_after_ms) for s in self.sensors.values()],
                               [b.name for b in config.buses])
        self.history.set_sensors(self)
        if old_alarms != [a for _, s in config.iter_sensors() for a in (s.name, s.alarms)]:
            # their states carried over from the transitions kept in memory
            self.alarms: Alarms = Alarms([a.row(s.name) for _, s in config.iter_sensors()
                                  for a in s.alarms], self.sensors, self.alarms.since(None))

    def start_bus(self, config: BusConfig) -> None:
        from .bus.frames import ring_size

        capture = self.config.capture
        frames = ring_size(capture.pre_s + capture.post_s, config.baudrate) \
            if capture is not None else None
        self.buses.start_one(config, frames)

    def hand_over_within(self, ms: int) -> None:
        """``hand_over_ms``: the buses' turns reach pushing front ends within ``ms``."""
        self.buses.writer.window = ms / 1000

    def index_buses(self) -> None:
        """The maps of buses and sensors, after buses were stopped and started."""
        self.runners = self.buses.runners
        self.masters = {name: runner.master for name, runner in self.runners.items()}
        self._runner_of = {s.name: self.runners[b.name] for b, s in self.config.iter_sensors()}

    def frontend(self, name: str) -> Frontend | None:
        found: Frontend | None = getattr(self, name)
        return found

    async def replace_frontend(self, name: str) -> None:
        """Stop the front end ``name`` and start one made from the current config (or
        none, when its section is gone); the supervisor watches the new one."""
        old = self.frontend(name)
        if old is not None:
            watcher = self._watchers.pop(name, None)
            if watcher is not None:
                watcher.cancel()
            try:
                await old.stop()
            except Exception:
                log.exception("%s: stopping it for a reload failed", name)
            self.cache.forget(old)
        config = self.config
        made: Frontend | None
        if name == "modbus":
            made = _modbus_server(self, config.modbus) if config.modbus else None
        elif name == "opcua":
            made = _opcua_server(self, config.opcua) if config.opcua else None
        else:
            made = self._mqtt_clients(config.mqtt)[name == "sparkplug"]
        setattr(self, name, made)
        self.frontends = [f for f in (self.modbus, self.http, self.opcua, self.mqtt,
                                      self.sparkplug) if f]
        if made is not None and self._running:
            made.arm()
            try:
                await made.start()
            except Exception as exc:  # (a port taken: the supervisor tries again)
                log.error("%s: could not start after the reload: %s", name, exc)
                made.fail(exc)
            self._watch(made)

    async def command(self, sensor: str, name: str,
                      args: Mapping[str, Any] | None = None) -> CommandResult:
        """Validate and carry out a command; returns after the sensor's answer."""
        config = self.sensors.get(sensor)
        if config is None:
            return CommandResult.failed(sensor, name, unknown_sensor(sensor))
        runner = self._runner_of[sensor]
        try:
            command = validate(name, args, config.series, runner.master.config.protocol)
            result = await runner.submit(sensor, command)
        except RequestFailed as exc:
            return CommandResult.failed(sensor, name, exc)
        if result.ok:  # what the answer shows of the settings, for the front ends
            self.cache.learn(sensor, CATALOGUE[name].learns(command.args, result.answer))
        return result

    async def start_frontends(self) -> None:
        """Open the listening sockets (once); raises ``StartupError`` when one cannot be
        bound."""
        for frontend in self.frontends:
            frontend.arm()
        servers: tuple[tuple[str, ModbusTcpServer | HttpServer | OpcUaServer | None], ...] = (
            ("modbus", self.modbus), ("http", self.http), ("opcua", self.opcua))
        for name, server in servers:
            if server is not None and not server.listening:
                try:
                    await server.start()
                except OSError as exc:
                    # asyncio's bind error has the errno but a long sentence of its own
                    reason = os.strerror(exc.errno) if exc.errno else str(exc)
                    raise StartupError(f"{name}.listen {server.config.listen}: {reason}") \
                        from None

    async def run(self, stop: asyncio.Event) -> None:
        """Run until ``stop`` is set, then stop: the front ends first (MQTT says
        "offline" while the buses still run; HTTP and Modbus TCP finish the requests
        they have, which may need a bus), then every bus after its exchange in flight.
        Each step runs even if one before it failed.  A front end that fails on the
        way is restarted by the supervisor; nothing a peer does ends this."""
        await self.start_frontends()
        if self.captures is not None:
            await self.captures.start()
        async with contextlib.AsyncExitStack() as stopping:  # unwinds last in, first out
            stopping.push_async_callback(self._stop_buses)
            self.buses.start()
            self._running = True
            # the front ends of the moment (a reload may have replaced some)
            stopping.push_async_callback(self._stop_frontends)
            if self.captures is not None:  # the one being collected, while MQTT is up
                stopping.push_async_callback(self.captures.stop)
            # (they connect in the background, retrying: never fail)
            for client in (self.mqtt, self.sparkplug):
                if client is not None:
                    await client.start()
            for frontend in self.frontends:
                self._watch(frontend)
            try:
                await self._watch_staleness(stop)
            finally:
                self._evaluating = False
                if self.journal_file is not None:
                    stopping.push_async_callback(asyncio.to_thread, self.journal_file.close)
                watchers = list(self._watchers.values())
                for watcher in watchers:
                    watcher.cancel()
                await asyncio.gather(*watchers, return_exceptions=True)
            log.info("stopping")

    def _watch(self, frontend: Frontend) -> None:
        self._watchers[frontend.name] = asyncio.create_task(
            self.supervisor.watch(frontend), name=f"watch {frontend.name}")

    async def _stop_frontends(self) -> None:
        """Last started, first stopped; each one even if one before it failed."""
        self._running = False
        for frontend in (self.sparkplug, self.mqtt, self.opcua, self.http, self.modbus):
            if frontend is not None:
                try:
                    await frontend.stop()
                except Exception:
                    log.exception("%s: stopping failed", frontend.name)

    async def _stop_buses(self) -> None:
        await self.buses.stop(SHUTDOWN_GRACE)

    async def _watch_staleness(self, stop: asyncio.Event) -> None:
        # one task waits for ``stop`` the whole time: ``wait_for(stop.wait(), tick)``
        # made a task per tick, and four turns of the loop to start and cancel it
        stopped = asyncio.ensure_future(stop.wait())
        try:
            while not stopped.done():
                self.cache.check_staleness()
                if self._evaluating:
                    self._check_communication()
                await asyncio.wait((stopped,), timeout=STALENESS_TICK)
        finally:
            stopped.cancel()

    async def read(self, sensor: str, max_age_ms: float) -> Snapshot:
        """The sensor's snapshot with a reading at most ``max_age_ms`` old: the bus is
        read first when the cached one is older (a streaming sensor's next frame
        serves).  Raises ``RequestFailed`` (``unknown_sensor``, ``offline``, …)."""
        snap = self.cache.snapshot(sensor)
        if snap.age_ms is not None and snap.age_ms <= max_age_ms:
            return snap
        runner = self._runner_of[sensor]
        await runner.read_now(sensor)
        return self.cache.snapshot(sensor)

    async def passthrough(self, sensor: str, pdu: bytes) -> bytes:
        """A Modbus PDU to a Modbus sensor's own registers (``raw_unit_id``).  A setting
        the exchange shows (a zero type written or read, a relative heading written) is
        noted as a command's would be: the map's registers 1000-1008 read it back
        whichever way it was set."""
        # a local import keeps this pass-through concern inside the method
        from .protocol.modbus_rtu import settings_shown

        runner = self._runner_of[sensor]
        answer = await runner.passthrough(sensor, pdu)
        self.cache.learn(sensor, settings_shown(pdu, answer))
        return answer

    async def bus_frames(self) -> dict[str, list[Frame]]:
        """Every line's recent frames (event capture), copied on the bus thread."""
        return {name: await runner.frames() for name, runner in self.runners.items()}

    async def watch_traffic(self, bus: str,
                            watcher: Callable[[Trace], None]) -> Callable[[], None]:
        """Tell ``watcher`` (on this loop) every exchange of ``bus`` from now on; returns
        what stops it.  The bus traces only while someone watches."""
        if bus not in self.runners:
            raise RequestFailed(ErrorKind.NOT_FOUND, f"no bus {bus!r} (the buses: "
                                f"{', '.join(self.runners) or 'none'})")
        return await self.runners[bus].watch(watcher)

    def scan(self, request: ScanRequest) -> ScanJob:
        """A scan of ``request.port``, not started yet (``ScanJob.start``): its ``bus``
        says which of the gateway's buses uses that port, paused for the scan."""
        bus = next((b.name for b in self.config.buses
                    if same_port(b.port, request.port)), None)
        if bus is None:
            return ScanJob(request, None)
        runner = self.runners[bus]
        return ScanJob(request, bus, runner.pause, runner.resume)

    def stats(self) -> list[BusStats]:
        return self.cache.bus_stats()

    def sensor_stats(self, name: str) -> SensorStats:
        return self.cache.sensor_stats(name)

    def frontend_stats(self) -> dict[str, FrontendCounts]:
        running = {"modbus": self.modbus, "mqtt": self.mqtt, "http": self.http,
                   "sparkplug": self.sparkplug, "opcua": self.opcua}
        return {name: {**f.stats(), "restarts": self.supervisor.restarts[name]}
                for name, f in running.items() if f is not None}


def _captures(gateway: Gateway) -> Captures:
    """Event capture, when configured: the buses keep their frames (enough of a full
    line for the whole window), the cache's events fill the sensors' rings."""
    from .bus.frames import ring_size
    from .capture import Captures

    config = gateway.config.capture
    assert config is not None
    for bus in gateway.config.buses:
        gateway.runners[bus.name].record_frames(
            ring_size(config.pre_s + config.post_s, bus.baudrate))
    captures = Captures(config, gateway.config, gateway.bus_frames, gateway.cache.catch_up)
    gateway.cache.subscribe(captures.on_cache_event, prompt=False)
    return captures


# Each front end's package is imported here, when the config has it (the module's
# docstring says why): one function each, so the types stay whole.

def _modbus_server(gateway: Gateway, config: ModbusConfig) -> ModbusTcpServer:
    from .frontends.modbus.server import ModbusTcpServer
    return ModbusTcpServer(gateway, config)


def _mqtt_client(gateway: Gateway, config: MqttConfig) -> MqttClient:
    from .frontends.mqtt.client import MqttClient
    return MqttClient(gateway, config)


def _sparkplug_client(gateway: Gateway, config: MqttConfig) -> SparkplugClient:
    from .frontends.sparkplug.client import SparkplugClient
    return SparkplugClient(gateway, config)


def _http_server(gateway: Gateway, config: HttpConfig) -> HttpServer:
    from .frontends.rest import HttpServer
    return HttpServer(gateway, config)


def _opcua_server(gateway: Gateway, config: OpcUaConfig) -> OpcUaServer:
    from .frontends.opcua.server import OpcUaServer
    return OpcUaServer(gateway, config)


async def run_until_signalled(config: GatewayConfig, stats_interval: float = 0.0,
                              on_started: Callable[[Gateway], None] | None = None,
                              source: ConfigSource | None = None) -> None:
    """``imu-gateway run``: the gateway until SIGINT or SIGTERM; SIGHUP reads the
    config file (``source``) again and applies it.  ``on_started`` is called once
    every listening socket is open."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)
    gateway = Gateway(config, source)
    reloads: set[asyncio.Task[Any]] = set()

    def on_hangup() -> None:
        task = loop.create_task(gateway.reloader.from_file(), name="reload")
        reloads.add(task)
        task.add_done_callback(reloads.discard)

    loop.add_signal_handler(signal.SIGHUP, on_hangup)
    log.info("%s", config.summary())
    for load in line_loads(config.buses):
        log.info("%s", load.describe())
        for warning in load.warnings():
            log.warning("%s", warning)
    await gateway.start_frontends()  # before the task group: a StartupError stays plain
    if on_started is not None:
        on_started(gateway)
    async with asyncio.TaskGroup() as tasks:
        if stats_interval > 0:
            tasks.create_task(_log_stats(gateway, stop, stats_interval))
        await gateway.run(stop)
    log.info("stopped")


async def _log_stats(gateway: Gateway, stop: asyncio.Event, interval: float) -> None:
    while not stop.is_set():
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), interval)
        for bus in gateway.stats():
            log.info("bus %s: %.1f transactions/s, utilisation %.2f, errors %s", bus.name,
                     bus.transactions_per_s, bus.utilisation, dict(bus.errors) or "none")


def openapi_json() -> str:
    """The REST API's OpenAPI document as committed at ``openapi/openapi.json``
    (``scripts/openapi`` writes it).  The routes do not depend on the config; a
    one-sensor gateway stands in for any."""
    from .frontends.rest import openapi_document

    config = config_from_dict({"gateway_id": "openapi", "buses": [{
        "name": "line", "port": "/dev/null", "protocol": "native",
        "sensors": [{"name": "sensor", "series": "AH"}]}]}, env={})
    document = openapi_document(Gateway(config), HttpConfig())
    return json.dumps(document, indent=2, ensure_ascii=False) + "\n"
