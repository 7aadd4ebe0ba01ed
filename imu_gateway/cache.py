"""The latest reading of every sensor, and how fresh it is.

The bus masters write here; the front ends only read here and listen for changes,
so a hundred clients cost the serial bus nothing.  The cache is passive: it never
calls a bus.  A front end that wants a reading no older than N ms asks the gateway
(``Gateway.read``), which asks the sensor's bus master.

Status, as clients see it:

* ``offline`` - the bus master cannot reach the sensor (or has not yet);
* ``stale``   - it is online but its latest reading is older than ``stale_after_ms``;
* ``ok``      - otherwise.

Staleness changes with time alone, so ``check_staleness()`` is called periodically
(the app does it) to turn that into status events.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import time
from collections import deque
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

from .alarms import AlarmEvent
from .errors import unknown_sensor
from .model import KnownSettings, Reading
from .normalise import Derivation
from .stats import BusStats, SensorStats

log = logging.getLogger("imu_gateway.cache")


class Status(enum.Enum):
    OK = "ok"
    STALE = "stale"
    OFFLINE = "offline"


@dataclass(frozen=True, slots=True)
class Snapshot:
    """One sensor as a client sees it at one moment."""

    name: str
    reading: Reading | None
    seq: int
    timestamp: datetime | None  # wall-clock time of the sample
    age_ms: float | None
    status: Status
    online: bool
    busy: bool  # a save or calibration is running
    streaming: bool  # the sensor's own auto-output feeds this reading
    errors: int  # timeouts, bad checksums, bad frames
    alarm: AlarmEvent | None = None  # only in an ``ALARM`` event: the transition

    @property
    def has_reading(self) -> bool:
        return self.reading is not None

    def to_json(self) -> dict[str, Any]:
        """The reading JSON (docs/mqtt.md; MQTT state and REST use the same)."""
        out: dict[str, Any] = {"sensor": self.name, "ts": iso_time(self.timestamp),
                               "seq": self.seq, "status": self.status.value}
        if self.reading is not None:
            out.update(self.reading.to_json_groups())
        return out


def iso_time(moment: datetime | None) -> str | None:
    """``2026-11-22T03:40:00.123Z``: UTC, milliseconds.  (``isoformat`` ends a UTC time
    with ``+00:00``, cut off for the ``Z``: half the time ``strftime`` took, and this
    is in every reading's JSON.)"""
    if moment is None:
        return None
    if moment.tzinfo is not UTC:
        moment = moment.astimezone(UTC)
    return moment.isoformat(timespec="milliseconds")[:-6] + "Z"


class EventKind(enum.Enum):
    READING = "reading"  # a new sample
    STATUS = "status"  # status, busy or streaming changed
    SETTINGS = "settings"  # the known settings changed (``Cache.settings``)
    ALARM = "alarm"  # an alarm's state changed: ``Snapshot.alarm`` says how


#: What a listener hears unless it asks for more (``Cache.subscribe``).
SENSOR_EVENTS = frozenset({EventKind.READING, EventKind.STATUS, EventKind.SETTINGS})
ALL_EVENTS = frozenset(EventKind)

Listener = Callable[[EventKind, Snapshot], None]
ErrorHook = Callable[[BaseException], None]


@dataclass(slots=True)
class _Entry:
    stale_after: float  # seconds
    reading: Reading | None = None
    seq: int = 0
    received: float = 0.0  # monotonic
    timestamp: datetime | None = None
    online: bool = False
    busy: bool = False
    streaming: bool = False
    errors: int = 0
    reported: tuple[Status, bool, bool] | None = None  # last status event sent
    reached: bool = False  # the bus has said what the sensor is: online, offline or a sample
    settings: KnownSettings = field(default_factory=KnownSettings)
    derivation: Derivation = field(default_factory=Derivation)  # its derived values


def _status(e: _Entry, now: float) -> Status:
    if not e.online:
        return Status.OFFLINE
    if e.reading is None or now - e.received > e.stale_after:
        return Status.STALE
    return Status.OK


#: How far back a reading's wall time may come out and still be taken for the two
#: clocks read a moment apart (``_wall_time``), s; more is the wall clock set back.
CLOCK_JITTER = 1.0


def _wall_time(stamp: float, before: datetime | None) -> datetime:
    """A reading's wall time: when it was received (``stamp``, from its monotonic time:
    a burst of turns handed over late keeps each sample's own time), never before the
    sensor's last one (the reading JSON's ``ts`` never goes back).  The monotonic and
    the wall clock are read one after the other, and a thread held between the two
    reads (a busy machine) puts ``stamp`` later by as much: the next sample's may then
    come out a little earlier than this one's.  A wall clock set back by more than
    ``CLOCK_JITTER`` is followed."""
    if before is not None and 0.0 < before.timestamp() - stamp < CLOCK_JITTER:
        return before
    return datetime.fromtimestamp(stamp, UTC)


class _Claim:
    """(``Cache.claim_prompt``) One claim, told apart from the others by identity;
    ``owner``: the object whose method is the prompt listener that made it (``forget``
    drops it with the listener)."""

    __slots__ = ("owner",)

    def __init__(self, owner: object = None) -> None:
        self.owner = owner


class Cache:
    def __init__(
        self,
        sensors: Iterable[tuple[str, float]],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``sensors``: (name, stale_after_ms) pairs.  ``clock`` must be the clock the
        bus masters time their readings with (the event loop's, by default monotonic)."""
        self._entries = {name: _Entry(stale_ms / 1000) for name, stale_ms in sensors}
        self._clock = clock
        self._listeners: list[tuple[Listener, ErrorHook | None, Collection[EventKind]]] = []
        # one per prompt listener, and one per ``claim_prompt``
        self._claims: list[_Claim] = []
        # Writes made elsewhere and not applied yet (a bus thread's turns): each source
        # applies its own, in order, when anything reads the cache (``catch_up``).
        self._sources: list[Callable[[], None]] = []
        self._catching_up = False
        # Events made while listeners hear another (an alarm a reading raised) wait for
        # it to reach them all: every listener hears every event in the same order.
        self._waiting: deque[tuple[EventKind, Snapshot]] = deque()
        self._delivering = False
        self._buses: dict[str, BusStats] = {}
        self._sensor_stats: dict[str, SensorStats] = {}

    @property
    def names(self) -> list[str]:
        return list(self._entries)

    def set_sensors(self, sensors: Iterable[tuple[str, float]], buses: Iterable[str]) -> None:
        """A reload: the sensors kept keep their entries (stale_after updated), new ones
        get one, and the sensors and buses gone are forgotten."""
        wanted, keep = dict(sensors), set(buses)
        self._entries = {name: self._entries.get(name) or _Entry(stale_ms / 1000)
                         for name, stale_ms in wanted.items()}
        for name, stale_ms in wanted.items():
            self._entries[name].stale_after = stale_ms / 1000
        self._buses = {n: b for n, b in self._buses.items() if n in keep}
        self._sensor_stats = {n: s for n, s in self._sensor_stats.items() if n in wanted}

    def _entry(self, name: str) -> _Entry:
        try:
            return self._entries[name]
        except KeyError:
            raise unknown_sensor(name) from None

    # ------------------------------------------------------------ reading

    @property
    def prompt(self) -> bool:
        """Whether a listener needs each event at once (the bus writes are then handed
        over per turn, ``bus.runner``); read from the bus thread."""
        return bool(self._claims)

    def add_source(self, drain: Callable[[], None]) -> None:
        """``drain()`` applies writes made elsewhere and not applied yet; every read
        runs it first, so a reader never sees older than what was handed over."""
        self._sources.append(drain)

    def catch_up(self) -> None:
        """Apply every write handed over and not applied yet, in order: on every read
        (a reader never sees older than the buses handed over, whatever the
        hand-over's window), by whoever answers from state kept outside the cache (the
        Modbus TCP register images), and by the hand-over itself, on the loop.  The
        listeners hear those writes inside the reader's call: a reader that also
        listens takes its snapshots before it listens (``snapshots``, the SSE
        stream's first events)."""
        if self._catching_up:  # (a write's listener reading: the rest come next)
            return
        self._catching_up = True
        try:
            for drain in self._sources:
                drain()
        finally:
            self._catching_up = False

    @contextlib.contextmanager
    def heard(self) -> Iterator[None]:
        """Reads within show what the listeners have heard: no waiting write is applied
        in them.  For a listener's own reads outside its events (a deferred send, an
        announcement after a connect): a write applied there would tell the listener
        a reading inside its own call, which it would then send a second time.  (What
        waits comes to it as events, next.)"""
        was, self._catching_up = self._catching_up, True
        try:
            yield
        finally:
            self._catching_up = was

    def snapshot(self, name: str) -> Snapshot:
        self.catch_up()
        return self._snapshot(name)

    def _snapshot(self, name: str) -> Snapshot:
        """(The writes' own: a write never applies other turns in its middle.)"""
        e = self._entry(name)
        now = self._clock()
        age = (now - e.received) * 1000 if e.reading is not None else None
        return Snapshot(name, e.reading, e.seq, e.timestamp, age, _status(e, now), e.online,
                        e.busy, e.streaming, e.errors)

    def snapshots(self, names: Iterable[str] | None = None) -> list[Snapshot]:
        """Every sensor (or ``names``) at one moment: caught up once, then no write
        applied between two of them."""
        self.catch_up()
        return [self._snapshot(name) for name in (self._entries if names is None else names)]

    def subscribe(self, listener: Listener, on_error: ErrorHook | None = None,
                  kinds: Collection[EventKind] = SENSOR_EVENTS,
                  prompt: bool = True) -> Callable[[], None]:
        """Call ``listener(kind, snapshot)`` on every change of ``kinds``; returns the
        unsubscriber.  ``ALARM`` events come only to a listener that asks for them
        (``kinds=ALL_EVENTS``).  Listeners run in the event loop and must not block.  An
        exception in one goes to its ``on_error`` (its front end's supervisor), or is
        logged: it never reaches the bus that published, nor the other listeners.

        ``prompt``: the listener pushes what it hears to the outside, so each event
        must reach it at once.  Without one, events come in bursts when something
        reads the cache (the staleness watch does every 0.1 s), at most
        ``bus.runner.LAZY_HAND_OVER`` late, each with its own times."""
        release = self.claim_prompt(getattr(listener, "__self__", None)) if prompt \
            else None
        entry = (listener, on_error, frozenset(kinds))
        self._listeners.append(entry)

        def unsubscribe() -> None:
            if entry in self._listeners:
                self._listeners.remove(entry)
                if release is not None:
                    release()

        return unsubscribe

    def claim_prompt(self, owner: object = None) -> Callable[[], None]:
        """Each event at once (as a prompt listener's) until the returned release is
        called: for a listener that pushes only while it has clients.  What waits for
        the lazy hand-over's timer is applied first: readers are never behind after."""
        self.catch_up()
        claim = _Claim(owner)
        self._claims.append(claim)

        def release() -> None:
            if claim in self._claims:
                self._claims.remove(claim)

        return release

    def forget(self, owner: object) -> None:
        """Unsubscribe every listener that is a method of ``owner`` (a front end a
        reload replaced)."""
        self._listeners = [e for e in self._listeners
                           if getattr(e[0], "__self__", None) is not owner]
        self._claims = [claim for claim in self._claims if claim.owner is not owner]

    # ------------------------------------------------------------ writing (bus masters)

    def publish(self, name: str, reading: Reading, at: float | None = None) -> int:
        """A new sample, received at monotonic time ``at``; returns its sequence number.
        Its derived values (tilt, vibration) are worked out here, once for every
        listener, on the main loop rather than the bus thread."""
        e = self._entry(name)
        e.seq += 1
        now, wall = self._clock(), time.time()
        e.received = now if at is None else at
        e.reading = e.derivation.complete(reading, e.received)
        e.timestamp = _wall_time(wall - max(0.0, now - e.received), e.timestamp)
        e.online = e.reached = True
        snap = self._snapshot(name)
        self._notify(EventKind.READING, snap)
        self._check(name, snap)
        return e.seq

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None:
        e = self._entry(name)
        if online is not None:
            e.online = online
            e.reached = True
            if not online:
                self._forget_settings(name, e)
        if busy is not None:
            e.busy = busy
            if not busy and e.settings.busy_with is not None:  # what it was busy with is over
                e.settings = replace(e.settings, busy_with=None)
                self._emit(EventKind.SETTINGS, name)
        if streaming is not None:
            e.streaming = streaming
        self._check(name)

    def count_error(self, name: str) -> None:
        self._entry(name).errors += 1

    def note_stats(self, bus: BusStats, sensors: Mapping[str, SensorStats]) -> None:
        """A bus master's counters, as it published them (frozen, made on its thread)."""
        self._buses[bus.name] = bus
        self._sensor_stats.update(sensors)

    def bus_stats(self) -> list[BusStats]:
        """Every bus's latest published counters, in the order they first came."""
        self.catch_up()
        return list(self._buses.values())

    def sensor_stats(self, name: str) -> SensorStats:
        """The sensor's latest published counters (its bus publishes before it runs)."""
        self._entry(name)  # an unknown sensor is refused as one
        self.catch_up()
        return self._sensor_stats[name]

    def learn(self, name: str, shown: KnownSettings) -> None:
        """Settings an answer showed (zero type, declination, …).  ``busy_with`` is
        kept only while the sensor is busy: the busy period starts before the command's
        answer is noted, and may be over (or never have begun: a calibration answered
        "complete") by then."""
        e = self._entry(name)
        if not e.busy:
            shown = replace(shown, busy_with=None)
        settings, e.settings = e.settings, e.settings.updated(shown)
        if e.settings != settings:
            self._emit(EventKind.SETTINGS, name)

    def _forget_settings(self, name: str, e: _Entry) -> None:
        """The sensor is offline, or its port is gone: it may be power-cycled and back at
        what it saved (a zero type set ``relative`` and never saved comes back
        ``absolute``), so what was learned of it is unknown until it is read again (its
        bus does that by itself when it answers again)."""
        forgotten = KnownSettings(busy_with=e.settings.busy_with)
        if e.settings != forgotten:
            e.settings = forgotten
            self._emit(EventKind.SETTINGS, name)

    def settings(self, name: str) -> KnownSettings:
        """The sensor's settings as far as the gateway knows them."""
        self.catch_up()
        return self._entry(name).settings

    def reached(self, name: str) -> bool:
        """Whether the bus has said what the sensor is (online, offline, or a sample):
        until then its "offline" only means "not tried yet"."""
        self.catch_up()
        return self._entry(name).reached

    def publish_alarm(self, event: AlarmEvent) -> None:
        """An alarm's transition, to the listeners of ``ALARM`` events, with its
        sensor's snapshot."""
        snap = replace(self._snapshot(event.state.sensor), alarm=event)
        self._notify(EventKind.ALARM, snap)

    def check_staleness(self) -> None:
        self.catch_up()
        for name in self._entries:
            self._check(name)

    def _check(self, name: str, made: Snapshot | None = None) -> None:
        """A status event, if status, busy or streaming changed since the last one.
        The state is worked out without a snapshot (this runs for every reading, and
        every tick for every sensor); the event's is ``made`` (the one the reading's
        listeners had), where it still shows the same reading and state."""
        e = self._entries[name]
        state = (_status(e, self._clock()), e.busy, e.streaming)
        if state != e.reported:
            e.reported = state
            same = made is not None and made.seq == e.seq and \
                (made.status, made.busy, made.streaming) == state
            self._notify(EventKind.STATUS, made if same and made is not None
                         else self._snapshot(name))

    def _emit(self, kind: EventKind, name: str) -> None:
        self._notify(kind, self._snapshot(name))

    def _notify(self, kind: EventKind, snap: Snapshot) -> None:
        if self._delivering:  # (a listener's doing, while it hears an event)
            self._waiting.append((kind, snap))
            return
        self._delivering = True
        try:
            self._deliver(kind, snap)
            while self._waiting:
                self._deliver(*self._waiting.popleft())
        finally:
            self._delivering = False
            self._waiting.clear()

    def _deliver(self, kind: EventKind, snap: Snapshot) -> None:
        for listener, on_error, kinds in list(self._listeners):
            if kind not in kinds:
                continue
            try:
                listener(kind, snap)
            except Exception as exc:  # one listener's fault stays its own
                if on_error is None:
                    log.exception("a cache listener failed")
                else:
                    on_error(exc)

