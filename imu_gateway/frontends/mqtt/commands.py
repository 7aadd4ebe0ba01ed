"""Commands that come in over MQTT, and their results.

A message on ``{prefix}/{sensor}/cmd/{command}`` with a JSON object is a command: it
goes to the gateway (which validates it and puts it in the bus master's queue) and its
result is published, to the MQTT 5 response topic when one is given, else to the
command's topic with ``/result`` appended.  A response topic where the gateway, Home
Assistant, Sparkplug B or the broker own the topics is refused (``ResponseTopics``).
A ``request_id`` in the payload (how an MQTT 3.1.1 client correlates: it has no
properties) is echoed in the result.  Retained and empty messages are never run
(docs/mqtt.md).  An alarm's acknowledgement (``…/{sensor}/alarm/{alarm}/ack``) goes
the same way (``take_ack``; its arguments: ``alarm_desk``).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.properties import Properties

from ...commands import CommandResult
from ...config import MqttConfig
from ...errors import ErrorKind, RequestFailed
from ...mqtt_link.message import Counters, Message, json_properties
from ...supervise import PeerLog
from ..common import GatewayLike, json_bytes, peer_json
from .alarm_desk import ack_result, acknowledger
from .topics import CONTROL_QOS

MAX_COMMANDS = 16  # commands carried out at once; more are answered "busy"
MAX_COMMAND_PAYLOAD = 64 * 1024  # bytes; the largest command's arguments are a few dozen
MAX_TOPIC_BYTES = 1024  # a response topic longer than this is not a mistake worth keeping
MAX_CORRELATION_BYTES = 1024
#: The in-band correlation an MQTT 3.1.1 client may send (it has no properties): a
#: short string or an integer, echoed in the result, never passed to the command.
REQUEST_ID = "request_id"
MAX_REQUEST_ID = 128
RequestId = str | int | None
#: The subtree of ``{base}/{gw}/`` where a peer may ask for its results.
REPLIES = "replies"
SPARKPLUG_NAMESPACE = "spBv1.0"


@dataclass(frozen=True)
class ResponseTopics:
    """Where a peer may have its command results published.

    The gateway publishes a result wherever an MQTT 5 response topic says.  On a topic
    that others read as the gateway's, Home Assistant's or Sparkplug's, a result would
    speak with their authority (a confused deputy: ``read_settings`` answered on a
    sensor's state topic).  So these are refused: the gateway's base topic (all of it:
    other gateways, the client-id claims) but for ``{base}/{gw}/replies`` and below, the
    discovery prefix, ``spBv1.0/``, and ``$`` topics (the broker's: a result there was
    lost without a word).  With a sensor named ``replies``, that subtree is the
    sensor's, and refused too."""

    base: str
    replies: str | None  # "{base}/{gw}/replies/"
    discovery_prefix: str

    @classmethod
    def of(cls, config: MqttConfig, gateway_id: str, sensors: Collection[str]) -> ResponseTopics:
        replies = None if REPLIES in sensors else f"{config.base_topic}/{gateway_id}/{REPLIES}/"
        return cls(config.base_topic, replies, config.discovery_prefix)

    def problem(self, topic: str) -> str | None:
        """Why a result may not go to ``topic`` (None: it may)."""
        if topic.startswith("$"):
            return "is a $ topic, the broker's own"
        if self.replies is not None and (topic.startswith(self.replies)
                                         or topic == self.replies.removesuffix("/")):
            return None
        instead = f"{self.replies}…" if self.replies is not None else "another topic"
        for prefix, owner in ((self.base, "the gateway's"), (self.discovery_prefix,
                              "Home Assistant's discovery"), (SPARKPLUG_NAMESPACE,
                              "Sparkplug B's")):
            if topic == prefix or topic.startswith(f"{prefix}/"):
                return f"is under {prefix}/, {owner}: ask for results on {instead}"
        return None


class CommandDesk:
    """Takes the command messages of one MQTT client, and answers each.

    ``send_control(message, key)`` queues a message that must not be dropped (a
    result, the clearing of a retained command) on the client's control queue."""

    def __init__(self, gateway: GatewayLike, config: MqttConfig,
                 send_control: Callable[[Message, str | None], None],
                 counters: Counters, peers: PeerLog) -> None:
        self.gateway = gateway
        self.config = config
        self.send_control = send_control
        self.counters = counters
        self._peers = peers
        self.tasks: set[asyncio.Task[None]] = set()  # commands being carried out
        self.response_topics = ResponseTopics.of(config, gateway.config.gateway_id,
                                                 gateway.sensors)
        self._clearing: set[str] = set()  # retained commands being cleared by us
        self._results = 0  # command results sent (their control-queue keys)

    def cancel(self) -> None:
        """Stop waiting for the commands in progress (the client is stopping)."""
        for task in list(self.tasks):
            task.cancel()
        self.tasks.clear()

    def take(self, message: paho.MQTTMessage, sensor: str, command: str) -> None:
        """A message on ``{prefix}/{sensor}/cmd/{command}``: carried out, answered."""
        if not self._runnable(message):
            return
        args, request_id, refused = self._request(message)
        if refused is not None:
            self._answer(message, CommandResult.failed(sensor, command, refused), request_id)
            return
        if len(self.tasks) >= MAX_COMMANDS:
            self._answer(message, CommandResult.failed(sensor, command, RequestFailed(
                ErrorKind.BUSY, f"{MAX_COMMANDS} commands are already being carried out")),
                request_id)
            return
        task = asyncio.create_task(self._carry_out(message, sensor, command, args,
                                                   request_id))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    def take_ack(self, message: paho.MQTTMessage, sensor: str, alarm: str) -> None:
        """A message on ``{prefix}/{sensor}/alarm/{alarm}/ack``: the alarm acknowledged
        (at once: it waits for no sensor), answered with its state after."""
        if not self._runnable(message):
            return
        args, request_id, refused = self._request(message)
        try:
            if refused is not None:
                raise refused
            state = self.gateway.acknowledge(sensor, alarm, acknowledger(args))
        except RequestFailed as exc:
            self._reply(message, ack_result(sensor, alarm, None, exc), request_id)
            return
        self._reply(message, ack_result(sensor, alarm, state), request_id)

    def _request(self, message: paho.MQTTMessage
                 ) -> tuple[dict[str, Any], RequestId, RequestFailed | None]:
        """A command's or an acknowledgement's arguments and request id (counted), or
        why it is refused (with the request id, when it had one to echo)."""
        self.counters.commands += 1
        request_id: RequestId = None
        try:
            args = _command_args(bytes(message.payload))
            request_id = _request_id(args)
            self._check_properties(message)
        except RequestFailed as exc:
            return {}, request_id, exc
        return args, request_id, None

    def _runnable(self, message: paho.MQTTMessage) -> bool:
        """Whether a message on a command topic asks for a command at all.

        A retained command would run again at every reconnect: it is never run, and
        is cleared once.  An empty payload is how anyone clears a retained message
        (the broker passes the clearing on to subscribers): it never runs either."""
        topic = message.topic
        if not message.payload:
            if topic in self._clearing:  # our own clearing, back from the broker
                self._clearing.discard(topic)
                return False
            self.counters.ignored += 1
            self._peers.warning("empty", "mqtt: an empty message on %s was not run: an "
                                "empty payload clears a retained message; send {} to run "
                                "a command", topic)
            return False
        if message.retain:
            self.counters.ignored += 1
            self._clearing.add(topic)
            self.send_control(Message(topic, b"", CONTROL_QOS, True), None)
            self._peers.warning("retained", "mqtt: a retained command on %s was not run, "
                                "and is cleared; publish commands without the retain "
                                "flag", topic)
            return False
        return True

    def _check_properties(self, message: paho.MQTTMessage) -> None:
        """Raise ``RequestFailed`` when the MQTT 5 properties of a command are unusable
        (logged: the asker may not be reading the default result topic)."""
        problem = _properties_problem(message.properties, self.response_topics)
        if problem is not None:
            self._peers.warning("refused properties", "mqtt: a command on %s was not run: "
                                "%s", message.topic, problem)
            raise RequestFailed(ErrorKind.BAD_ARGUMENTS, problem)

    async def _carry_out(self, message: paho.MQTTMessage, sensor: str, command: str,
                         args: Mapping[str, Any], request_id: RequestId) -> None:
        result = await self.gateway.command(sensor, command, args)
        self._answer(message, result, request_id)

    def _answer(self, request: paho.MQTTMessage, result: CommandResult,
                request_id: RequestId = None) -> None:
        self._reply(request, result.to_json(), request_id)

    def _reply(self, request: paho.MQTTMessage, body: dict[str, Any],
               request_id: RequestId = None) -> None:
        """Publish a result (``body``, with ``ok``) where the request asks for it."""
        if not body["ok"]:
            self.counters.command_errors += 1
        # MQTT 5: the asker's response topic and correlation data win, where usable
        # (_check_properties refused the request otherwise, answered here).
        topic, properties = f"{request.topic}/result", json_properties(self.config)
        if _properties_problem(request.properties, self.response_topics) is None:
            topic = getattr(request.properties, "ResponseTopic", None) or topic
            correlation = getattr(request.properties, "CorrelationData", None)
            if correlation is not None:  # (only MQTT 5 carries it: properties exist)
                assert properties is not None
                properties.CorrelationData = correlation
        if request_id is not None:
            body[REQUEST_ID] = request_id
        self._results += 1
        self.send_control(Message(topic, json_bytes(body),
                                  max(self.config.qos, 1), False, properties),
                          f"result {self._results}")


def _command_args(payload: bytes) -> dict[str, Any]:
    """A command's arguments: a JSON object (blank: none)."""
    if len(payload) > MAX_COMMAND_PAYLOAD:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"the payload is {len(payload)} bytes; "
                            f"at most {MAX_COMMAND_PAYLOAD}")
    if not payload.strip():
        return {}
    try:
        args = peer_json(payload)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"the payload is not JSON: {exc}") from None
    if not isinstance(args, dict):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, "the payload must be a JSON object")
    return args


def _request_id(args: dict[str, Any]) -> RequestId:
    """Takes the in-band ``request_id`` out of the arguments (``RequestFailed`` when it
    is neither a short string nor an integer)."""
    if REQUEST_ID not in args:
        return None
    value = args.pop(REQUEST_ID)
    if isinstance(value, bool) or not isinstance(value, str | int) or \
            (isinstance(value, str) and len(value) > MAX_REQUEST_ID):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"{REQUEST_ID} must be a string of at "
                            f"most {MAX_REQUEST_ID} characters, or an integer")
    return value


def topic_problem(topic: str) -> str | None:
    """Why a topic from a peer (an MQTT 5 response topic) cannot be published to."""
    if not topic:
        return "is empty"
    if "+" in topic or "#" in topic:
        return "has a wildcard (+ or #); results go to one topic"
    if "\0" in topic:
        return "has a NUL character"
    size = len(topic.encode("utf-8", "surrogatepass"))
    if size > MAX_TOPIC_BYTES:
        return f"is {size} bytes long; at most {MAX_TOPIC_BYTES}"
    return None


def _properties_problem(properties: Properties | None,
                        allowed: ResponseTopics) -> str | None:
    response = getattr(properties, "ResponseTopic", None)
    if response is not None:
        problem = topic_problem(str(response)) or allowed.problem(str(response))
        if problem is not None:
            return f"the response topic {str(response)[:60]!r} {problem}"
    correlation = getattr(properties, "CorrelationData", None)
    if correlation is not None and len(correlation) > MAX_CORRELATION_BYTES:
        return (f"the correlation data is {len(correlation)} bytes; "
                f"at most {MAX_CORRELATION_BYTES}")
    return None
