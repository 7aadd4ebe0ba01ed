"""paho-mqtt driven from the gateway's event loop: no network thread.

paho's ``loop_start()`` runs a thread of its own, and every ``publish()`` from the
event loop then wakes it through a socket pair, which writes the message; its
callbacks hand their events back with ``call_soon_threadsafe``.  Per message that
is two thread switches, about half of what MQTT costs a sample
(docs/benchmarks.md).  paho supports an external loop instead
(``loop_read``/``loop_write``/``loop_misc``): ``Driver`` is that loop, on asyncio.

* **Reading**: the socket is watched with ``add_reader``; each event reads one
  packet (``loop_read``), and paho's callbacks run there, on the event loop.  A
  TLS socket may hold decrypted bytes while its descriptor has nothing more to
  read (``pending()``): then the read goes on at the loop's next turn.
* **Writing**: ``publish()`` only queues the packet (paho does not write itself
  while ``on_socket_register_write`` is set) and asks for a write; the queue is
  written at the end of the loop's current turn, so a burst of messages costs one
  callback.  What the socket does not take (its buffer is full: a broker that
  stops reading) stays in paho's queue, in order, and is written when
  ``add_writer`` says the socket takes more; nothing is lost or reordered.
* **Keepalive**: ``loop_misc()`` once a second sends PINGREQ when due, and drops
  a connection whose broker has not answered for the keepalive, as paho's thread
  did.
* **The end**: paho tells when it closes the socket (``on_socket_close``: a lost
  connection, a DISCONNECT written, or ``close()``); the loop stops watching it
  before it closes.

The connect (DNS, TCP, TLS, CONNECT) is blocking in paho and stays in an executor:
``attach`` is called after it, on the event loop.  paho writes the CONNECT itself
during ``connect()``, as no write callback is set yet.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as paho

#: seconds between two calls of ``loop_misc`` (keepalive; paho's thread: one)
MISC_S = 1.0


def close_sockets(client: paho.Client) -> None:
    """paho 2.2 leaves the socket of a failed or lost connection to the garbage
    collector; ``_reset_sockets`` (private, but the one place that closes it, and a
    wake-up socket pair had ``loop()`` made one) closes it now."""
    with contextlib.suppress(OSError):
        client._reset_sockets()


class Driver:
    """One connected paho client's network loop, on the running event loop."""

    def __init__(self, client: paho.Client, progress: Callable[[], None] = lambda: None
                 ) -> None:
        self.client = client
        #: called after each read and write: what paho wrote or had acknowledged is
        #: published now (``MQTTMessageInfo.is_published``)
        self._progress = progress
        self._loop = asyncio.get_running_loop()
        self._fd: int | None = None  # the socket watched, until paho closes it
        self._writer = False  # add_writer is on: the socket's buffer was full
        self._write_soon = False  # a write is due at the end of this turn
        self._misc: asyncio.TimerHandle | None = None

    def attach(self) -> None:
        """Start driving the client: its ``connect()`` has returned."""
        sock = self.client.socket()
        if sock is None:
            return
        self._fd = sock.fileno()
        self.client.on_socket_close = self._closing
        self.client.on_socket_register_write = self._write_asked
        self._loop.add_reader(self._fd, self._read)
        self._misc = self._loop.call_later(MISC_S, self._keepalive)
        self._read_pending()  # (bytes a TLS handshake left decrypted)
        if self.client.want_write():  # what connect() could not write
            self._write_asked()

    def flush(self) -> None:
        """Write what paho has queued, as far as the socket takes it now."""
        self._write()

    def close(self) -> None:
        """Write what can be written at once (a DISCONNECT), then stop and close the
        client's socket (also when ``attach`` never came: a failed connect's)."""
        if self._fd is not None:
            self._write()
        close_sockets(self.client)
        self._detach()

    # ------------------------------------------------------------ the loop's events

    def _read(self) -> None:
        if self._fd is None:  # (a read asked for before paho closed the socket)
            return
        self.client.loop_read()  # on an error paho closes the socket (_closing)
        self._progress()
        self._read_pending()

    def _read_pending(self) -> None:
        sock = self.client.socket()
        pending = getattr(sock, "pending", None)
        if self._fd is not None and pending is not None and pending() > 0:
            self._loop.call_soon(self._read)

    def _write_asked(self, *_: Any) -> None:
        """paho queued a packet (its ``on_socket_register_write``)."""
        if not self._write_soon and not self._writer:
            self._write_soon = True
            self._loop.call_soon(self._write)

    def _write(self) -> None:
        self._write_soon = False
        if self._fd is None:
            return
        self.client.loop_write()
        self._progress()
        if self._fd is None:  # the write failed: paho closed the socket
            return
        full = self.client.want_write()
        if full and not self._writer:
            self._loop.add_writer(self._fd, self._write)
        elif not full and self._writer:
            self._loop.remove_writer(self._fd)
        self._writer = full

    def _keepalive(self) -> None:
        self.client.loop_misc()
        if self._fd is not None:
            self._misc = self._loop.call_later(MISC_S, self._keepalive)

    def _closing(self, *_: Any) -> None:
        """paho is about to close the socket: stop watching it first."""
        self._detach()

    def _detach(self) -> None:
        if self._fd is not None:
            self._loop.remove_reader(self._fd)
            self._loop.remove_writer(self._fd)
            self._fd, self._writer = None, False
        if self._misc is not None:
            self._misc.cancel()
            self._misc = None
