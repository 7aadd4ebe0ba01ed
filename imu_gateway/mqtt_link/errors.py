"""The MQTT transport's exceptions: a branch of ``imu_gateway.errors``'s tree.

    MqttLinkError
     ├── BrokerUnreached  a broker was not reached (no connection, no answer)
     └── ProbeFailed      a broker answered the probe before a connect, but with a
                          refusal, or not all the way

Both are the link's to raise and the front end's to word for its log: the session
(``session.py``) and the probe (``probe.py``) raise them, the MQTT and Sparkplug clients
say what they mean to a person.
"""

from __future__ import annotations

from ..config import Broker
from ..errors import GatewayError


class MqttLinkError(GatewayError):
    """Base of everything the MQTT transport raises on purpose."""


class BrokerUnreached(MqttLinkError):
    """An MQTT broker was not reached: ``kind`` is ``"unreachable"`` (no TCP or TLS
    connection; ``detail`` says why), ``"silent"`` (no CONNACK in time) or
    ``"closed"`` (closed before answering).  ``broker`` names it when it is not the
    one whose turn it was (a hedged probe's).  The MQTT client words it for the log."""

    def __init__(self, kind: str, detail: str = "", broker: Broker | None = None) -> None:
        super().__init__(kind, detail)
        self.kind, self.detail, self.broker = kind, detail, broker


class ProbeFailed(MqttLinkError):
    """A probe ``broker`` answered, but with a refusal or not all the way (``cause``):
    the real connect goes there, and says why."""

    def __init__(self, broker: Broker, cause: Exception) -> None:
        super().__init__(broker, cause)
        self.broker, self.cause = broker, cause
