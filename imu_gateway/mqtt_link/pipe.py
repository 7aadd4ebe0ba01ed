"""The way from the MQTT front ends to paho: a bounded outbox, control messages that are
never dropped, and a window of messages in paho's hands (see the docstring of
``frontends/mqtt/client.py``)."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

import paho.mqtt.client as paho
from paho.mqtt.enums import MQTTErrorCode

from ..supervise import PeerLog
from .message import Counters, Message

KEEPALIVE_S = 30
WINDOW = 100  # messages handed to paho and not yet written or acknowledged
#: messages handed to paho and none written for this long: publishing does not work
STALLED_S = 2 * KEEPALIVE_S


class Outbox:
    """A bounded FIFO: when full, the oldest message goes and is counted."""

    def __init__(self, size: int) -> None:
        self._messages: deque[Message] = deque()
        self.size = size
        self.dropped = 0

    def put(self, message: Message) -> None:
        self._messages.append(message)
        if len(self._messages) > self.size:
            self._messages.popleft()
            self.dropped += 1

    def put_back(self, message: Message) -> None:
        """A message paho refused: first in line again."""
        self._messages.appendleft(message)

    def take(self) -> Message:
        return self._messages.popleft()

    def clear(self) -> None:
        self.dropped += len(self._messages)
        self._messages.clear()

    def __len__(self) -> int:
        return len(self._messages)


class Pipe:
    """The way to paho: retained control messages and results first (one per key,
    never dropped), then the bounded ``Outbox`` of states; at most ``WINDOW`` of them
    in paho's hands and not yet written or acknowledged.

    ``client()`` is the paho client of the connection, ``connected()`` whether there
    is one now.  All on the event loop (paho's callbacks run there too: driver.py)."""

    def __init__(self, queue_size: int, counters: Counters, peers: PeerLog,
                 client: Callable[[], paho.Client | None],
                 connected: Callable[[], bool]) -> None:
        self.outbox = Outbox(queue_size)
        # Retained control messages (status, availability, discovery) and command
        # results go before the outbox and are never dropped: one entry per key, so
        # this is bounded by the number of topics (and of commands in progress).
        self.control: dict[str, Message] = {}
        self.counters = counters
        self._peers = peers
        self._client = client
        self._connected = connected
        # Messages in paho's hands: each is done when paho says it is published.
        # Asked after each of the driver's reads and writes (``settle``) rather than
        # told by paho's ``on_publish``: for each QoS 0 message written, paho builds a
        # ReasonCode and a Properties (its tables of every property name) only to call
        # it, a seventh of what MQTT costs a sample (docs/benchmarks.md).  QoS 0 ones
        # are written in the order handed; the others (results, few) wait for their
        # acknowledgements, each on its own: one never acknowledged holds one place.
        self._unwritten: deque[paho.MQTTMessageInfo] = deque()
        self._unacknowledged: list[paho.MQTTMessageInfo] = []
        self._window_full = False  # drain stopped at a full window: settle drains
        # (written, when) at the last progress seen: the stall watch's (``publishing``)
        self._progress: tuple[int, float] = (0, 0.0)
        self._stale: list[Message] = []  # states of before the last connect

    def settle(self) -> None:
        """Count what paho has written or had acknowledged since; what waited for room
        in the window goes on."""
        unwritten, before = self._unwritten, self.in_window()
        while unwritten and unwritten[0].is_published():
            unwritten.popleft()
        if self._unacknowledged:
            self._unacknowledged = [i for i in self._unacknowledged if not i.is_published()]
        self.counters.written += before - self.in_window()
        if self._window_full and self.in_window() < WINDOW:
            self.drain()

    def connected_anew(self) -> None:
        """What paho held when the last connection went is lost with it (each
        connection has a fresh client): counted, then the window starts empty.  The
        states still waiting are old news by now: set aside, before anything drains
        (the state desk takes them: ``waiting``)."""
        self.counters.lost_in_flight += self.in_window()
        self._unwritten.clear()
        self._unacknowledged.clear()
        while self.outbox:
            self._stale.append(self.outbox.take())

    def empty(self) -> bool:
        return not (self.control or self.outbox or self.in_window())

    def waiting(self) -> list[Message]:
        """Takes the states set aside at the connect."""
        messages, self._stale = self._stale, []
        return messages

    def queued(self) -> int:
        return len(self.outbox) + len(self.control)

    def in_window(self) -> int:
        return len(self._unwritten) + len(self._unacknowledged)

    def send(self, message: Message) -> None:
        """Queue a message and send what the window allows."""
        self.outbox.put(message)
        self.drain()

    def send_control(self, message: Message, key: str | None = None) -> None:
        """A message that must not be dropped; a newer one for the same ``key`` (its
        topic by default) replaces one still waiting."""
        self.control.pop(key or message.topic, None)
        self.control[key or message.topic] = message
        self.drain()

    def drain(self) -> None:
        """Hand paho what the window allows: control messages first, then the outbox."""
        self._window_full = False
        while (self.control or self.outbox) and self._connected():
            if self.in_window() >= WINDOW:
                self._window_full = True
                return
            if self.control:
                key = next(iter(self.control))
                if not self._hand_to_paho(self.control[key]):
                    return
                del self.control[key]
            else:
                message = self.outbox.take()
                if not self._hand_to_paho(message):
                    self.outbox.put_back(message)
                    return

    def _hand_to_paho(self, message: Message) -> bool:
        """True when the message is done with: handed to paho, or dropped because
        paho can never send it (it must not block the queue behind it); False when
        paho refused it for now (no connection), to be tried again."""
        client = self._client()
        assert client is not None
        try:
            info = client.publish(message.topic, message.payload, message.qos,
                                        message.retain, message.properties)
        except (ValueError, TypeError) as exc:
            self.counters.undeliverable += 1
            self._peers.warning("undeliverable", "mqtt: dropped a message to %.80r: %s",
                                message.topic, exc)
            return True
        if info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS:
            if not self.in_window():  # the wait starts now
                self._progress = (self.counters.written, asyncio.get_running_loop().time())
            (self._unacknowledged if message.qos else self._unwritten).append(info)
            self.counters.published += 1
            return True
        return False

    def publishing(self) -> bool:
        """Connected, and what was handed to paho is being written: messages in its
        hands with none written for ``STALLED_S`` mean a connection that only looks
        up (a broker that stopped reading)."""
        if not self._connected():
            return False
        now, written = asyncio.get_running_loop().time(), self.counters.written
        if written != self._progress[0]:
            self._progress = (written, now)
        if not self.in_window():
            return True
        return now - self._progress[1] < STALLED_S
