"""``docs/opcua.md``, generated from the address space's rows (``space``) and the
command catalogue: ``python -m imu_gateway.frontends.opcua.docs > docs/opcua.md``.
``tests/frontends/opcua/test_opcua_docs.py`` fails while the committed file differs."""

from __future__ import annotations

from asyncua.common.connection import TransportLimits

from ...commands import CATALOGUE, argument_type, commands_for
from ...model import CAPABILITIES, VALUE_GROUPS, Series, WireProtocol
from .conditions import EVENT_IDS_KEPT, SEVERITY
from .guard import (
    MAX_PUBLISHING_INTERVAL_MS,
    MAX_SUBSCRIPTION_LIFETIME_S,
    MAX_SUBSCRIPTIONS_PER_SESSION,
)
from .history import HISTORY_DOC
from .identity import MANUFACTURER, PRODUCT_NAME, PRODUCT_URI
from .live import RELOAD_DOC
from .methods import declared_type
from .nodes import COMMON_GROUPS
from .sampling import MAX_QUEUE_SIZE, SAMPLING_STEP_MS
from .server import CALL_STATUS, MAX_CLIENTS
from .space import BUS_VARS, IDENTITY_VARS, NEVER_READ, QUALITY, SENSOR_VARS, UNECE, UNITS

INTRO = """# OPC UA

Generated from `imu_gateway/frontends/opcua/` by
`python -m imu_gateway.frontends.opcua.docs`; do not edit by hand.

With an `opcua:` section the gateway serves its sensors to OPC UA clients (SCADA, MES,
historians): [asyncua](https://github.com/FreeOpcUa/opcua-asyncio) in the gateway's
own event loop. It reads the gateway's cache like every front end: a Read or a
subscription never waits for the serial bus, and a hundred clients cost the bus
nothing. Methods (the commands) go through the bus master's command queue. Tested
with asyncua's client (its high-level one, and sessions built by hand from its
low-level one) and Node's node-opcua.

```yaml
# fragment: a section shown alone, not a whole config
opcua:
  listen: 0.0.0.0:4840         # opc.tcp://HOST:4840/
  allow_none: false            # true: also security mode None
  anonymous: true              # false: only the users below
  users: {operator: "${OPCUA_PASSWORD}"}
  allow_commands: false        # true needs anonymous: false
  pki_dir: opcua-pki           # server_cert.der and server_key.pem (made at the
                               # first start), trusted/: client certificates,
                               # rejected/: the ones refused, to move to trusted/
```

## What is supported, and what is not

- **Supported:** Read, Browse, TranslateBrowsePaths, subscriptions to data changes,
  Call (the commands), HistoryRead of the measured values (raw and processed, see
  "History"), the alarms as Part 9 conditions with their events, Acknowledge and
  ConditionRefresh (see "Alarms and conditions"), GetEndpoints and FindServers;
  security policies None (only with `allow_none`) and Basic256Sha256 Sign and
  SignAndEncrypt; anonymous and user name tokens.
- **Not supported:** writing values (every variable is read-only; a setting is
  changed by its method), the parts of Part 9 that "Alarms and conditions" lists as
  not supported, HistoryRead of events, OPC UA PubSub, X.509 user tokens, the Aes
  policies, and discovery through a Local Discovery Server. The server's `ServerProfileArray`
  names the profiles whose facets it implements; it is not certified (no conformance
  test tool has run on it).

## Address space

Namespace `urn:imu-gateway`. Every node the gateway adds has a string NodeId in it:
the path of browse names below its root, joined by dots. A client's tag list
survives a restart and a reordered config, and no node of the gateway is mixed in with
namespace 0's numeric ids (the standard properties `EURange` and `EngineeringUnits`
keep their browse names in namespace 0, as Part 8 names them, and their NodeIds are
the gateway's: `…Angles.pitch.EURange`):

```
Objects/IMU Gateway/{gateway_id}/                ns=N;s={gateway_id}
    Sensors/{sensor}/  (an ImuSensorType)         ns=N;s={gateway_id}.Sensors.{sensor}
        {Group}/{field}                           …Sensors.{sensor}.Angles.pitch
            EURange, EngineeringUnits             …Sensors.{sensor}.Angles.pitch.EURange
        Status, Sequence, Errors, Series, Protocol, Address
        {command}()                               with allow_commands
        Alarms/{alarm}  (a condition)             …Sensors.{sensor}.Alarms.boom_lean
    Buses/{bus}/{counter}                         …Buses.{bus}.Transactions
Types/ObjectTypes/BaseObjectType/ImuSensorType    ns=N;s=ImuSensorType
```

### The sensor type

`ImuSensorType` (a subtype of BaseObjectType, `ns=N;s=ImuSensorType`) declares what a
sensor may have, so a SCADA builds one template (a UDT) on it and applies it to every
sensor. Each sensor object's TypeDefinition is it.

| part | modelling rule |
|---|---|
{type_rows}
| Status, Sequence, Errors, Series, Protocol, Address | Mandatory |
| Alarms (the folder of the alarms' conditions) | Mandatory |
| each command's method | Optional (with `allow_commands`, where the series has it) |

A sensor has only the optional parts its series has: an IMU has no Angles, a VG no
MagneticField. A sensor's age is not a variable: it is now minus the value's
SourceTimestamp (a variable of it would be right only at the moment it was written).

"""

SECURITY = """
## Security

- **Endpoints:** Basic256Sha256 with Sign and with SignAndEncrypt; security mode None
  only with `allow_none: true`.
- **A channel with no security** is opened for any client, but with `allow_none:
  false` it serves discovery only: GetEndpoints and FindServers (what a client asks
  before it picks a secured endpoint). Every other request on it, CreateSession
  first, is answered `BadSecurityModeRejected` and logged. (asyncua alone would serve
  a whole session there; the gateway checks each request first.)
- **A user token** must name (`PolicyId`) a user token policy of the endpoint its
  channel is on, of its own type. A password that policy says to encrypt (on Sign,
  and on None: Basic256Sha256, RSA-OAEP) sent in clear or otherwise is
  `BadIdentityTokenInvalid`, even a right one. On SignAndEncrypt the channel
  encrypts it already, and the policy says so.
- **A session moves** to a new channel (after a connection loss) only with the client
  certificate that created it; another client's channel gets
  `BadSecurityChecksFailed`, whatever token it brings.
- **CreateSession on a secured channel** must name the certificate the channel was
  opened with (`BadSecurityChecksFailed`), and that certificate must be trusted
  (`BadCertificateUntrusted`; asyncua checked only a certificate the request named,
  when it named one).
- **An encrypted password** must end with the nonce the server gave its session last
  (Part 4 7.41.2.3): one seen on a Sign channel cannot be replayed in another session
  (`BadIdentityTokenInvalid`).
- **A session not activated** gets `BadSessionNotActivated` for everything but the
  session services; a connection holds one (a second CreateSession closes the first),
  and a connection with none activated after 10 s is closed.
- **RegisterServer** is `BadServiceUnsupported`: the gateway is no discovery server.
- **A subscription is its session's** (Part 4 5.13): another session, anonymous or
  not, gets `BadSubscriptionIdInvalid` for it in DeleteSubscriptions,
  ModifySubscription, SetPublishingMode, Republish, the monitored-item services and a
  Publish's acknowledgements, as if it did not exist (asyncua found a subscription by
  its id alone, and ids count 1, 2, 3: any session could delete or silence a SCADA
  client's subscription). TransferSubscriptions takes another session's subscription
  only for the same user (the same user name; both anonymous: the same client
  certificate), else `BadUserAccessDenied` for that id; the session it was taken from
  is told (`Good_SubscriptionTransferred`), on a publish request it has waiting or
  else on its next one. A Publish from a session with no subscription, and no such
  notice to take, is `BadNoSubscription` (asyncua kept it unanswered).
- **ModifySubscription** is applied, revised within the limits below: the publishing
  interval (the next publish comes one new interval after the Modify; 0 or less is
  the fastest, 10 ms), the lifetime and keep-alive counts; the lifetime starts again.
  (asyncua answered the values the subscription was created with, and changed
  nothing.)
- **Limits:** {clients} clients at once; {subs} subscriptions a session, a publishing
  interval of at most {interval:g} s (a longer one is revised down) and a lifetime of
  at most {lifetime:g} s; a closed session's subscriptions are deleted, whatever the
  CloseSession asked (a client cannot leave them behind to hold the server's); a
  message chunk larger than the receive buffer ({buffer} bytes) is refused from its
  header (`BadTcpMessageTooLarge`) and the connection closed.
- **Monitored items' queues** (Part 4 7.21): a value's requested queueSize of 0 or 1 is
  a queue of one value, the newest (a client that wants every sample of a fast sensor
  asks more than its publishing interval holds, say 10); an event item's 0 is
  {queue}; none is more than {queue}, the revised queueSize says so. (asyncua made 0
  its cap of 10 000 for both: a client that asked the default and published slowly had
  every sample queued for it.)
- **The server's certificate** is made at the first start (self-signed, one year) in
  `pki_dir`, with the key; a client trusts it once (or you replace both files by a
  certificate of your own CA). It names the application URI
  (`urn:imu-gateway:{{gateway_id}}`), the host name, and the address listened on; with
  `0.0.0.0` every address of the host (so a client that connects by IP address finds
  it there). When the gateway finds a name missing from the one it made (the host's
  addresses changed) or the certificate expired, it makes a new one and says so in the
  log: clients trust the new one. A certificate not made by the gateway is never
  replaced.
- **Client certificates** are accepted only if they are in `pki_dir/trusted/` (DER or
  PEM), or signed by a CA certificate there, read again when the folder changes (no
  restart). An empty folder refuses every secured connection and says so in the log.
  A certificate refused as untrusted is saved in `pki_dir/rejected/`
  (`{{common name}} [{{SHA-1}}].der`; at most 100 files of 16 KiB, 1 MiB in all): move
  it to `trusted/` to accept that client, as in UaExpert or open62541.
- **The log:** at the gateway's default level an OPC UA start is a few lines; asyncua
  says only its warnings, each kind at most once a minute, and so does the gateway of
  the requests it refuses (`--log-level debug` shows everything).
- **Users:** `users` (name → password; write `${{VAR}}` to keep the password out of the
  file). `anonymous: false` refuses clients without a user name; with
  `allow_commands: true` the config insists on it.
"""


def _type_rows() -> str:
    rows = []
    for group, spec in VALUE_GROUPS.items():
        rule = "Mandatory" if group in COMMON_GROUPS else "Optional"
        rows.append(f"| {spec.title} (each field Mandatory within it) | {rule} |")
    return "\n".join(rows)


def _identity() -> list[str]:
    return ["## What the server says of itself", "",
            f"- **BuildInfo:** ProductName `{PRODUCT_NAME}`, ProductUri `{PRODUCT_URI}`, "
            f"ManufacturerName `{MANUFACTURER}`, SoftwareVersion and BuildNumber the "
            "package's version, BuildDate the time of the installed package's files.",
            "- **ServerCapabilities:** every variable has a value: the profiles, the "
            "locale (`en`), MinSupportedSampleRate 0 (a value is sampled when the gateway "
            "writes it), no continuation points for Browse or Query (their answers are "
            "whole), the string and message limits of the transport, the session and "
            "subscription limits; the aggregates of HistoryRead under AggregateFunctions; "
            "`Auditing` false.", ""]


def _values() -> list[str]:
    lines = ["### Measured values", "",
             "Each an `AnalogItemType` variable of type Double (the value as the sensor "
             "gave it: 32.52 reads 32.52, not the 32.52000045776367 a Float would widen "
             "to), with `EURange` (the largest value the sensor's native format carries) "
             "and `EngineeringUnits` (UNECE "
             f"Recommendation 20, namespace `{UNECE}`). Only the groups a series measures "
             "are there, and the groups derived from them (Tilt and Vibration: "
             "[alarms.md](alarms.md#derived-values)); a derived value that has none now "
             "(the vibration before a second of ten samples, the direction of no tilt) is "
             "NaN.", "",
             "| folder | variables | unit (UNECE code, UnitId) | EURange | series |",
             "|---|---|---|---|---|"]
    for group, spec in VALUE_GROUPS.items():
        unit = UNITS[group]
        shown = f"{unit.name} (`{unit.code}`, {unit.unit_id})" if unit else "none"
        who = ", ".join(s.name for s in Series if group in CAPABILITIES[s].groups)
        lines.append(f"| {spec.title} | {', '.join(spec.fields)} | {shown} | "
                     f"±{spec.span} | {who} |")
    return lines


def _quality() -> list[str]:
    return ["", "### Timestamps and quality", "",
            "A value's SourceTimestamp is the wire time of its sample (when its answer came "
            "off the line), not when it was published; the ServerTimestamp is when it was "
            "written into the address space, which is when a client looks: a sensor's "
            "newest sample is written at the next request, publish or sampling tick of "
            "any client (into a value a monitored item takes with sampling interval 0, "
            "each sample as it comes, within 0.1 s and at most 0.25 s with no MQTT, "
            "Sparkplug or live stream on). Its StatusCode says how the sensor is:",
            "",
            "| sensor | StatusCode |", "|---|---|",
            *(f"| {status.value} | `{code}` |" for status, code in QUALITY.items()),
            f"| never read since the start | `{NEVER_READ}` (the value is null or NaN) |", "",
            "A Read gets the newest sample; a sample that came between two looks is "
            "written only into the values an item takes every value of, since no client "
            "could see it elsewhere (a 100 Hz sensor read every 100 ms is written ten "
            "times a second, not a hundred; with an item taking every pitch, its pitch a "
            "hundred times and its other values ten). A monitored item "
            "gets the samples at its sampling interval (below), at the publishing interval "
            "of its subscription. A value that repeats (a sensor at rest) changes only its "
            "timestamp: ask for the DataChangeTrigger StatusValueTimestamp (and sampling "
            "interval 0) to get every sample, or watch `Sequence`, which changes with "
            "each.", ""]


def _sampling() -> list[str]:
    return ["### Monitored items' sampling", "",
            "Each monitored item of a value is sampled at its own sampling interval (OPC UA "
            "Part 4 5.12.1.2), which the server answers (revisedSamplingInterval) in "
            "CreateMonitoredItems and ModifyMonitoredItems, and uses:", "",
            "| requested samplingInterval | revised, and what the item gets |", "|---|---|",
            "| 0 | 0: every sample written (the fastest practical rate) |",
            f"| more than 0 | rounded up to a multiple of {SAMPLING_STEP_MS:g} ms, at most "
            f"{MAX_PUBLISHING_INTERVAL_MS / 1000:g} s: at most one value an interval, the "
            "newest written by then |",
            "| negative (-1) | the subscription's publishing interval, when the item is "
            f"created or modified (at least {SAMPLING_STEP_MS:g} ms; a publishing interval "
            "of 0: 0) |", "",
            "- A change between two samples is not seen: only the value at the sampling "
            "time. A value written and then left as it is (a sensor gone offline: its bad "
            "StatusCode) is still sampled, at most one interval after it was written.",
            "- A new item reports its value at once, then at its interval; a Modify takes "
            "effect from its answer (an item modified to 0 gets the value held for it at "
            "once).",
            "- The sampled values then go through the item's filter (trigger, deadband) "
            "and queue (queueSize: see \"Security\") as every value did.",
            "- An item of events (alarms) is not sampled: it gets every event.",
            "- Sampling saves the server's work: a client that asks 250 ms of a 100 Hz "
            "sensor costs it four values a second an item, not a hundred "
            "([benchmarks.md](benchmarks.md), \"CPU per sample in the front ends\"). "
            "Mind that asyncua's client asks 50 ms unless told otherwise.", ""]


def _rows(title: str, rows: list[tuple[str, str, str]]) -> list[str]:
    return [title, "", "| variable | type | what it says |", "|---|---|---|",
            *(f"| {n} | {t} | {d} |" for n, t, d in rows), ""]


def _methods() -> list[str]:
    lines = ["### Methods (`allow_commands: true`)", "",
             "Each sensor object has the catalogue's commands its series and protocol have "
             "([commands.md](commands.md)): one input argument (or none) and a `result` "
             "string out. A call is checked before the sensor hears of it (Part 4, "
             "5.11.2): a method its object does not have is `BadMethodInvalid`; more "
             "arguments than the method has `BadTooManyArguments`; fewer "
             "`BadArgumentsMissing`; one of the wrong type `BadInvalidArgument`, with "
             "`BadTypeMismatch` in its InputArgumentResults (a Double argument takes any "
             "number, an Int32 any integer, a String only a String). The type's "
             "declaration of a method, called on a sensor, runs that sensor's own.", "",
             "A refused or failed command is the call's StatusCode:", "",
             "| why | StatusCode |", "|---|---|",
             *(f"| {kind.value} | `{code}` |" for kind, code in CALL_STATUS.items()),
             "", "| method | argument | series (native / Modbus RTU) |", "|---|---|---|"]
    for spec in CATALOGUE.values():
        kind = argument_type(spec)
        arg = "none" if kind is None else f"{spec.argument} ({declared_type(spec)})"
        where = [", ".join(s.name for s in Series if spec.name in commands_for(s, p)) or "none"
                 for p in WireProtocol]
        lines.append(f"| {spec.name} | {arg} | {' / '.join(where)} |")
    return [*lines, ""]


def _alarms() -> list[str]:
    severities = ", ".join(f"{s.value} {n}" for s, n in SEVERITY.items())
    return ["### Alarms and conditions", "",
            "Each alarm ([alarms.md](alarms.md#alarms)) is a condition object in its "
            "sensor's `Alarms` folder, `ns=N;s={gateway_id}.Sensors.{sensor}.Alarms.{alarm}` "
            "(its ConditionId), with a HasCondition reference from the sensor:", "",
            "- a configured alarm is an `ExclusiveLimitAlarmType`, with the properties "
            "`HighLimit` (`above`) and `LowLimit` (`below`) as configured (only those "
            "configured);",
            "- the `communication` alarm is an `OffNormalAlarmType`.", "",
            "**Notifiers.** The Server object, the gateway object (`ns=N;s={gateway_id}`) and "
            "each sensor object have EventNotifier SubscribeToEvents, with HasNotifier "
            "references Server → gateway → sensor. An event item on a sensor gets that "
            "sensor's alarms; on the gateway object or the Server, every sensor's.", "",
            "**An event at each transition** (raised, cleared, acknowledged; none per "
            "sample), of the condition's type, with these fields (select them by browse "
            "path on the type, as Part 9 names them):", "",
            "| field | what it says |", "|---|---|",
            "| EventId | new for each event (ByteString, 16 bytes) |",
            "| EventType | `ExclusiveLimitAlarmType` (i=9341) or `OffNormalAlarmType` "
            "(i=10637) |",
            "| SourceNode, SourceName | the sensor object, the sensor's name |",
            "| Time | the transition's time; ReceiveTime: when the event was made |",
            "| Message | `boom/boom_lean active_unacked: pitch 10 (limit 5)`: the alarm, its "
            "state as in alarms.md, the value against the limit (who acknowledged, for "
            "an acknowledgement) |",
            f"| Severity, LastSeverity | {severities} |",
            "| ConditionId (the NodeId attribute of ConditionType) | the condition object |",
            "| ConditionName | the alarm's name |",
            "| ConditionClassId | ProcessConditionClassType; SystemConditionClassType "
            "for `communication` |",
            "| Retain | true while the alarm is not `normal` (active, or not yet "
            "acknowledged) |",
            "| ActiveState, ActiveState/Id | `Active`/`Inactive`, true/false; "
            "ActiveState/TransitionTime: when it became active |",
            "| AckedState, AckedState/Id | `Acknowledged`/`Unacknowledged`, true/false |",
            "| EnabledState, EnabledState/Id | `Enabled`, true (always) |",
            "| Quality | Good |",
            "| LimitState/CurrentState (and /Id) | `High` or `Low` while active (the limit "
            "crossed), empty otherwise |",
            "| HighLimit, LowLimit | as configured |",
            "| InputNode | the watched variable (`…Angles.pitch`; `…Status` for "
            "`communication`) |",
            "| Value | the value of the transition that raised or cleared it (Double; "
            "an acknowledgement keeps the raise's, as in alarms.md; none for "
            "`communication`): **not a Part 9 field**, the gateway's own, "
            "selected by the browse path `Value` |",
            "| Comment, ClientUserId | the latest acknowledgement's comment; who "
            "acknowledged (`operator (opcua 10.0.0.5)`) |", "", *_alarm_methods()]


def _alarm_methods() -> list[str]:
    """What a client may call on the alarms, and what of Part 9 is not there."""
    return ["**Acknowledge** (`AcknowledgeableConditionType`'s `Acknowledge`, i=9111, "
            "called with the ConditionId as the ObjectId, as Part 9 says every server "
            "must take it: node-opcua's `session.acknowledgeCondition` does so) with "
            "(EventId, Comment):", "",
            "- only with `allow_commands: true` (which needs users): otherwise "
            "`BadUserAccessDenied`, for every session;",
            f"- the EventId must be one of the condition's last {EVENT_IDS_KEPT} events "
            "(the one a client saw): else `BadEventIdUnknown`; an ObjectId that is no "
            "condition: `BadNodeIdUnknown`; the arguments missing or too many: "
            "`BadArgumentsMissing`, `BadTooManyArguments`; of the wrong type: "
            "`BadInvalidArgument`;",
            "- an alarm `normal` or acknowledged already (nothing to acknowledge, REST's "
            "409): `BadConditionBranchAlreadyAcked`;",
            "- it acknowledges the alarm (not one event of it: the gateway keeps no "
            "branches), as the user of the session (`operator (opcua 10.0.0.5)` in the "
            "journal); the acknowledged event follows.", "",
            "**ConditionRefresh** (i=3875, and ConditionRefresh2, i=12912, with a "
            "MonitoredItemId that is ignored) on the Server object, with a SubscriptionId: "
            "a RefreshStartEvent, every condition whose Retain is true (its latest event, "
            "same EventId), and a RefreshEndEvent, to the event items of that "
            "subscription. At start the alarms' states are those the journal left "
            "(alarms.md, \"The journal\"), so a refresh tells what is still to handle "
            "after a restart. An unknown SubscriptionId, or another session's, is "
            "`BadSubscriptionIdInvalid`.", "",
            "**Not supported** of Part 9: the condition objects have their type, limits "
            "and the HasCondition reference, but not the type's state variables and "
            "methods as nodes (read the state from the events, or a ConditionRefresh; "
            "the gateway's asyncua builds no condition instances); Enable, Disable, "
            "AddComment, Confirm (no ConfirmedState), Shelving, Suppression, "
            "OutOfService, Silence, branches (BranchId is null), the Audit events, "
            "HistoryRead of events. A Where clause is asyncua's: Equals, the "
            "comparisons, IsNull, Between, InList, And, Or and Not work; OfType matches "
            "the exact type only (OfType AlarmConditionType drops an "
            "ExclusiveLimitAlarmType's event: test EventType InList instead, as asyncua's "
            "client does); Like drops every event it tests, Cast is taken as true. A "
            "subscription's event queue is asyncua's: a client that does not publish "
            "loses the oldest events first.", "",
            "**Why some of it is the gateway's own code.** asyncua 2.1 gives an event "
            "only to the items on the node it names as its emitter, not to those on the "
            "notifiers above it (the gateway gives each event to the sensor's, the "
            "gateway's and the Server's items); it binds no Acknowledge; and its "
            "ConditionRefresh resends only to items on an event's last emitter. The "
            "gateway's code for these is in `imu_gateway/frontends/opcua/conditions.py`.",
            ""]


def markdown() -> str:
    sensor_rows = [(v.name, v.datatype, v.description) for v in (*SENSOR_VARS, *IDENTITY_VARS)]
    bus_rows = [(v.name, v.datatype, v.description) for v in BUS_VARS]
    security = SECURITY.format(
        clients=MAX_CLIENTS, subs=MAX_SUBSCRIPTIONS_PER_SESSION,
        interval=MAX_PUBLISHING_INTERVAL_MS / 1000, lifetime=MAX_SUBSCRIPTION_LIFETIME_S,
        buffer=TransportLimits().max_recv_buffer, queue=MAX_QUEUE_SIZE)
    lines = [INTRO.replace("{type_rows}", _type_rows()), *_values(), *_quality(), *_sampling(),
             *_rows("### A sensor's status and identity", sensor_rows),
             *_rows("### Buses (written every second)", bus_rows), *_methods(),
             *_alarms(), HISTORY_DOC, RELOAD_DOC, *_identity(), security]
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown(), end="")
