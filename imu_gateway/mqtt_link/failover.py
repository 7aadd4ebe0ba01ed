"""Which broker to connect to next, and after how long: sans-IO, time as an argument.

``mqtt.url`` may name several brokers (the nodes of a cluster).  The rules:

* The gateway connects to the first.  It stays on the broker it is connected to for
  as long as that connection lasts: no falling back to the first when it returns (a
  cluster's nodes are equals, and a move costs a republish of everything retained).
* When a connection that worked is lost, the next broker in the list is tried after
  ``RECONNECT_MIN`` (the lost one may be the one that is down).
* Before a reconnect (after a lost connection or a failed try), the plain MQTT front
  end probes the brokers (``probe.py``): a probe that has no answer after half a
  second gets another beside it on the next broker of the list (the same one, when
  the list has one), and the connect goes to the first that answered.
* When a try fails, the next broker is tried at once, until every broker of the list
  has failed in a row: then the gateway waits, from ``RECONNECT_MIN`` doubling to
  ``RECONNECT_MAX``, before the next round.  With one broker this is the plain
  back-off.
"""

from __future__ import annotations

from ..config import Broker

RECONNECT_MIN, RECONNECT_MAX = 0.5, 30.0  # seconds between rounds of connection attempts


class Failover:
    """The broker to try now (``current``), and the wait before the next try."""

    def __init__(self, brokers: tuple[Broker, ...]) -> None:
        assert brokers, "at least one broker"
        self.brokers = brokers
        self.index = 0
        self.failures = 0  # tries failed in a row since the last connection that worked
        self.delay = RECONNECT_MIN  # the wait after the next whole round that fails

    @property
    def current(self) -> Broker:
        return self.brokers[self.index]

    def order(self) -> tuple[Broker, ...]:
        """Every broker, from ``current`` on: the order a hedged probe tries them in."""
        return self.brokers[self.index:] + self.brokers[:self.index]

    def move_to(self, broker: Broker) -> None:
        """``broker`` answered first (a hedged probe): it is the one tried now."""
        self.index = self.brokers.index(broker)

    def ended(self, worked: bool) -> float:
        """The try of ``current`` ended: it connected and was lost (``worked``), or it
        failed.  Moves on to the next broker; returns the seconds to wait first."""
        self.index = (self.index + 1) % len(self.brokers)
        if worked:
            self.failures, self.delay = 0, RECONNECT_MIN
            return RECONNECT_MIN
        self.failures += 1
        if self.failures % len(self.brokers):
            return 0.0  # the rest of the round, at once
        wait, self.delay = self.delay, min(self.delay * 2, RECONNECT_MAX)
        return wait
