"""The primary host's STATE, as the edge node takes it: sans-IO.  The rules (stated
for users in docs/sparkplug.md, "Primary host"):

* Sparkplug 3.0's ``spBv1.0/STATE/{host}`` carries JSON ``{"online": …, "timestamp": …}``.
  A STATE whose timestamp is older than the newest one taken is ignored, online or
  offline (3.0: ``message-flow-edge-node-birth-publish-phid-wait-timestamp`` and
  ``operational-behavior-edge-node-termination-host-offline-timestamp``): a will or a
  retained message of an earlier host session, delivered late.  An equal timestamp is
  taken: a 3.0 host's will carries the timestamp of the birth it ends.
* Sparkplug 2.2's ``STATE/{host}`` (``ONLINE``/``OFFLINE``, no timestamp) counts only
  while no 3.0 STATE was ever heard from this host: a host that speaks 3.0 leaves the
  2.2 topic behind, often with an ``OFFLINE`` retained on it for good, and the two
  would otherwise take turns deciding (a birth and death loop).
* What the host said is kept per connection: each new connection waits for a STATE
  of its own (the retained one comes at once).  The newest timestamp, and whether the
  host speaks 3.0, are kept for the life of the process.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from .node import NAMESPACE


@dataclass(frozen=True, slots=True)
class HostState:
    """One STATE message, read."""

    online: bool
    timestamp: int | None  # Sparkplug 3.0's, ms since the epoch; None: not given
    legacy: bool  # on 2.2's topic


def read_state(data: bytes, legacy: bool) -> HostState | str:
    """A STATE payload: 3.0's JSON or 2.2's plain ``ONLINE``/``OFFLINE``; else why it
    is not one."""
    try:
        doc = json.loads(data)
    except ValueError:
        text = data.strip().upper()
        if text in (b"ONLINE", b"OFFLINE"):
            return HostState(text == b"ONLINE", None, legacy)
        return "a primary host STATE that is neither JSON nor ONLINE/OFFLINE"
    online = doc.get("online") if isinstance(doc, dict) else None
    if not isinstance(online, bool):
        return 'a primary host STATE without a boolean "online"'
    stamp = doc.get("timestamp")
    good = isinstance(stamp, int) and not isinstance(stamp, bool)
    return HostState(online, stamp if good else None, legacy)


class PrimaryHost:
    """Which of a primary host's STATE messages count, and what the last said."""

    def __init__(self, host_id: str) -> None:
        self.host_id = host_id
        # 3.0's first: subscribed in this order, a retained 3.0 STATE arrives before a
        # retained 2.2 one, so a host that speaks 3.0 is known before 2.2's is read
        self.topics = (f"{NAMESPACE}/STATE/{host_id}", f"STATE/{host_id}")
        self.online = False  # what the last STATE taken on this connection said
        self.newest: int | None = None  # the newest 3.0 timestamp taken
        self.speaks_3 = False  # a STATE was heard on 3.0's topic

    def connected(self) -> None:
        """A new connection: offline until one of its STATE messages says online."""
        self.online = False

    def heard(self, topic: str, data: bytes) -> str | None:
        """A message on one of ``topics``: None when taken (``online`` says what it
        said), else why it is ignored."""
        state = read_state(data, legacy=topic == self.topics[1])
        if isinstance(state, str):
            return state
        if state.legacy and self.speaks_3:
            return (f"a Sparkplug 2.2 STATE on {topic} ({'ONLINE' if state.online else 'OFFLINE'}):"
                    f" {self.host_id} speaks 3.0, so only {self.topics[0]} counts")
        if not state.legacy:
            self.speaks_3 = True
        if state.timestamp is not None:
            if self.newest is not None and state.timestamp < self.newest:
                return (f"a primary host STATE older than the newest taken (timestamp "
                        f"{state.timestamp} < {self.newest}): a late one")
            self.newest = state.timestamp
        self.online = state.online
        return None
