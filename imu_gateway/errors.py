"""Every error the gateway raises on purpose, in one tree, and the one vocabulary its
front ends answer with.

    GatewayError
     ├── ConfigError      the config is unusable: every problem, one line each
     ├── StartupError     the gateway cannot start (a port to listen on is taken, …)
     ├── LinkError        a serial port cannot be opened, or is gone
     ├── ProtocolError    (imu_gateway/protocol/errors.py: the protocol layer's own tree)
     │    ├── FrameError  the peer sent bytes no document allows (routine on a noisy line)
     │    └── UsageError  our caller asked for a frame the protocol cannot express
     ├── MqttLinkError    (imu_gateway/mqtt_link/errors.py: the MQTT transport's own)
     │    ├── BrokerUnreached  a broker was not reached (no connection, no answer)
     │    └── ProbeFailed      a broker answered the probe before a connect, but with a
     │                         refusal, or not all the way
     ├── RequestFailed    a client's request was not carried out; ``kind`` says why
     ├── BadCommand       (imu_gateway/simulator/control.py) a simulator control command
     │                    that cannot be carried out
     └── InitError        (imu_gateway/tools/init.py) a bad answer or option of
                          ``imu-gateway init``

A ``RequestFailed`` is what a command, an on-demand read or a pass-through ends in
when it cannot be done, whichever front end asked.  Its ``kind`` is one row of
``KINDS``: the name every front end shows (REST's and MQTT's ``kind``), the HTTP
status REST answers with, and the Modbus exception code Modbus TCP answers with.
Library errors are turned into these where the library is called: pyserial's in
``bus/link.py``, pydantic's in ``config/problems.py`` and ``commands.py`` (FastAPI's, for
query parameters, in ``frontends/rest/routes.py``), pymodbus's in
``protocol/modbus_rtu.py``.

Nothing here imports anything of the gateway at run time but ``modbus_codes`` (a
leaf): every layer may raise these.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from .modbus_codes import (
    DEVICE_BUSY,
    DEVICE_FAILURE,
    GATEWAY_PATH,
    ILLEGAL_ADDRESS,
    ILLEGAL_VALUE,
    TARGET_FAILED,
)


class GatewayError(Exception):
    """Base of every error the gateway raises on purpose."""


class ConfigError(GatewayError):
    """The config is unusable.  ``problems``: one line each, ``<yaml path>: <message>``."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


class StartupError(GatewayError):
    """The gateway cannot start (a port to listen on is taken, …): one line for the user."""


class LinkError(GatewayError):
    """The port cannot be opened, or is gone."""


class ErrorKind(enum.Enum):
    """Why a request failed: the names every front end shows (rows in ``KINDS``)."""

    UNKNOWN_COMMAND = "unknown_command"
    UNKNOWN_SENSOR = "unknown_sensor"
    BAD_ARGUMENTS = "bad_arguments"
    UNSUPPORTED = "unsupported"
    BUSY = "busy"
    TIMEOUT = "timeout"
    OFFLINE = "offline"
    FAILURE = "failure"
    UNCONFIRMED = "unconfirmed"
    NO_READING = "no_reading"
    TOO_MANY_STREAMS = "too_many_streams"
    TOO_LARGE = "too_large"
    UNAUTHORISED = "unauthorised"
    FORBIDDEN = "forbidden"
    REQUEST_TIMEOUT = "request_timeout"
    HEADERS_TOO_LARGE = "headers_too_large"
    NOT_FOUND = "not_found"
    METHOD_NOT_ALLOWED = "method_not_allowed"
    UNKNOWN_ALARM = "unknown_alarm"
    NOTHING_TO_ACKNOWLEDGE = "nothing_to_acknowledge"
    TOO_MANY_ATTEMPTS = "too_many_attempts"
    TOO_MANY_WATCHERS = "too_many_watchers"




@dataclass(frozen=True, slots=True)
class KindRow:
    """How one kind of failure is told: its HTTP status, its Modbus exception code
    (``None``: Modbus TCP has no request that fails so), and what it means."""

    status: int
    modbus: int | None
    meaning: str


KINDS: Mapping[ErrorKind, KindRow] = MappingProxyType({
    ErrorKind.UNKNOWN_COMMAND: KindRow(404, ILLEGAL_ADDRESS, "no command of that name"),
    ErrorKind.UNKNOWN_SENSOR: KindRow(404, GATEWAY_PATH, "no sensor of that name or unit"),
    ErrorKind.BAD_ARGUMENTS: KindRow(422, ILLEGAL_VALUE, "the arguments are not valid"),
    ErrorKind.UNSUPPORTED: KindRow(
        422, ILLEGAL_ADDRESS, "the sensor's series or protocol has no such command"),
    ErrorKind.BUSY: KindRow(409, DEVICE_BUSY, "the sensor is saving or calibrating"),
    ErrorKind.TIMEOUT: KindRow(504, TARGET_FAILED, "the sensor did not answer"),
    ErrorKind.OFFLINE: KindRow(504, TARGET_FAILED, "the sensor or its port is gone"),
    ErrorKind.FAILURE: KindRow(502, DEVICE_FAILURE, "the sensor answered that it failed"),
    # Sent, and maybe carried out: not "did not answer" (0B), which a client may take
    # as leave to send it again.  04, as for a failure: look before writing again.
    ErrorKind.UNCONFIRMED: KindRow(
        502, DEVICE_FAILURE, "the command was sent but its answer was lost: read the "
        "setting back before sending it again"),
    ErrorKind.NO_READING: KindRow(503, TARGET_FAILED, "the sensor has not been read yet"),
    ErrorKind.TOO_MANY_STREAMS: KindRow(503, None, "every event stream is taken"),
    ErrorKind.TOO_LARGE: KindRow(413, None, "the request body is too large"),
    ErrorKind.UNAUTHORISED: KindRow(401, None, "a valid bearer token is required"),
    ErrorKind.FORBIDDEN: KindRow(403, None, "commands are turned off, or the role is too low"),
    ErrorKind.REQUEST_TIMEOUT: KindRow(408, None, "the request did not come in time"),
    ErrorKind.HEADERS_TOO_LARGE: KindRow(431, None, "the request line and headers are too large"),
    ErrorKind.NOT_FOUND: KindRow(404, None, "no such path"),
    ErrorKind.METHOD_NOT_ALLOWED: KindRow(405, None, "the path does not take that method"),
    ErrorKind.UNKNOWN_ALARM: KindRow(404, ILLEGAL_ADDRESS, "the sensor has no alarm of that name"),
    # Acknowledging an alarm that is normal, or acknowledged already: nothing was done,
    # and the client's picture of the alarm is out of date (a conflict, as for busy).
    ErrorKind.NOTHING_TO_ACKNOWLEDGE: KindRow(
        409, ILLEGAL_VALUE, "the alarm is normal or acknowledged already: nothing to "
        "acknowledge"),
    ErrorKind.TOO_MANY_ATTEMPTS: KindRow(429, None, "too many logins from this address: "
                                         "wait Retry-After seconds"),
    ErrorKind.TOO_MANY_WATCHERS: KindRow(429, None, "too many traffic monitors open from "
                                         "this address: close one"),
})


class RequestFailed(GatewayError):
    """A command, read or pass-through was not carried out; ``kind`` says why, the
    message says it for a person."""

    def __init__(self, kind: ErrorKind, message: str) -> None:
        super().__init__(message)
        self.kind = kind

    @property
    def status(self) -> int:
        return KINDS[self.kind].status


def unknown_sensor(name: str) -> RequestFailed:
    """The one way every front end words a sensor it does not know."""
    return RequestFailed(ErrorKind.UNKNOWN_SENSOR, f"unknown sensor {name!r}")
