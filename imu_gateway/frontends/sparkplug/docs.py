"""``docs/sparkplug.md``, generated from the metric rows (``metrics``) and the node's
rules (``node``): ``python -m imu_gateway.frontends.sparkplug.docs > docs/sparkplug.md``.
``tests/frontends/sparkplug/test_sparkplug_docs.py`` fails while the committed file differs."""

from __future__ import annotations

from ...commands import CATALOGUE
from ...config import SensorConfig
from ...model import CAPABILITIES, VALUE_GROUPS, Series, WireProtocol
from .client import ACK_BY, NODE_DATA_EVERY_S, REBIRTH_HOLD_S
from .metrics import (
    ALARM_ROWS,
    BUS_ROWS,
    STATUS_ROWS,
    VALUE_TYPE,
    DataType,
    command_rows,
    command_type,
    identity_rows,
)
from .node import BDSEQ, NAMESPACE, REBIRTH

INTRO = """# Sparkplug B

Generated from `imu_gateway/frontends/sparkplug/` by
`python -m imu_gateway.frontends.sparkplug.docs`; do not edit by hand.

With an `mqtt.sparkplug` section the gateway is a Sparkplug B edge node on the brokers
of `mqtt.url`: its `gateway_id` is the edge node id, each sensor a device (its name is
the device id). It speaks Sparkplug 3.0 with the Eclipse Tahu protobuf payload, on an
MQTT session of its own (client id `imu-gateway-{{gateway_id}}-sparkplug`, its will the
NDEATH), beside the plain topics of [mqtt.md](mqtt.md) or instead of them
(`plain_topics: false`). It reads the gateway's cache like every front end: no bus
traffic of its own. Tested against Eclipse Tahu's decoder (npm `sparkplug-payload`).

```yaml
# fragment: a section shown alone, not a whole config
mqtt:
  url: mqtt://broker:1883
  sparkplug:
    group_id: plant-a            # required
    plain_topics: true           # false: Sparkplug only
    allow_commands: false        # DCMD runs the catalogue's commands when true
    primary_host_id: scada       # births wait for spBv1.0/STATE/scada to say online
    bdseq_file: /var/lib/imu-gateway/bdseq   # bdSeq kept across restarts
```

## What is supported, and what is not

- **Supported:** the edge node and its devices (NBIRTH, NDEATH, DBIRTH, DDEATH,
  NDATA, DDATA), aliases, seq and bdSeq, NCMD `Node Control/Rebirth`, DCMD commands,
  the alarms' states as metrics and their acknowledgement by DCMD,
  one primary host's STATE (3.0's JSON on `spBv1.0/STATE/{{host}}`, and 2.2's
  `STATE/{{host}}`), broker failover across `mqtt.url`.
- **Not supported:** templates and DataSets, metric properties other than `engUnit`,
  historical metrics (store and forward: what the broker missed is not replayed),
  payload compression, `Node Control/Next Server` and the other node controls but
  Rebirth, Sparkplug A, and acting as a host application.

## Messages

{messages}

- **seq** is 0 in the NBIRTH and one more, modulo 256, in every DBIRTH, DDATA, DDEATH
  and NDATA after it.
- **bdSeq** is one more (modulo 256) in every MQTT CONNECT packet the node sends (the
  will in it, the NDEATH, carries the number). A try that sends none (the broker is
  down and refuses the TCP connection) takes none: after an outage the next CONNECT
  carries the next number, however many tries failed. The NBIRTH of a connection
  carries its CONNECT's. With `bdseq_file` it is kept across restarts, so that a will
  the broker publishes late for a killed gateway never matches the new session's
  birth; without it, each start begins at 0.
- **Timestamps**: every payload and every metric has one (ms since the epoch). A
  sensor's metrics carry their sample's wire time; the node's metrics and a command's
  `Commands/Result` the time they are sent; the NDEATH's `{bdseq}` the time its
  connection was made.
- **Aliases** are unique within the node and stable for the life of the process.
- All births and data are QoS 0 and not retained, as Sparkplug asks; states that could
  not be sent while the broker was away are not replayed (a new session begins with
  births).

## Commands

- **NCMD** `{ns}/{{group}}/NCMD/{{gateway_id}}` with `{rebirth}` = true: the NBIRTH and
  every DBIRTH again (same bdSeq, seq from 0). While a primary host is awaited
  (below), a rebirth is ignored and counted: the host's coming back births the node.
- **DCMD** `{ns}/{{group}}/DCMD/{{gateway_id}}/{{sensor}}`: writing a `Commands/…`
  metric runs that command of the catalogue ([commands.md](commands.md)) through the
  bus master's command queue, when `allow_commands` is true (otherwise the DCMD is
  ignored, and counted, and the births carry no command metrics). A command without
  an argument is run by writing true. The outcome comes back as the device's
  `Commands/Result` metric in a DDATA: `{{command}}: ok`, followed by the sensor's
  answer as JSON when it has one, or `{{command}}: {{kind}}: {{message}}` (the error
  kinds REST and MQTT answer with). `read_settings` answers with the settings read:
  `read_settings: ok {{"zero_type": "absolute", "declination": 0.0, "address": 0}}`.
- A write the node refuses before it reaches the bus gets a `Commands/Result` too,
  and runs nothing: a metric that is not a command
  (`{{metric}}: unknown_command: …`), a value of the wrong datatype
  (`set_address: bad_arguments: Commands/set_address is Int32; the DCMD wrote a String`;
  an Int32 command takes a whole Float or Double too), no value, or false.
- Writing true to an alarm's `Alarms/{{alarm}}/Acked` acknowledges it (below,
  [Alarms](#alarms)).
- Anything else (not a Sparkplug payload, an unknown device, a DCMD while commands
  are not allowed) is ignored, counted and logged (rate-limited); the node goes on.

## A reload

A reload that adds, removes or changes sensors (`SIGHUP`, `PUT /api/v1/config`:
[configuration.md](configuration.md), "Changing the config while running") is a
rebirth on the same MQTT session, as for a Rebirth NCMD: no new CONNECT, the same
bdSeq, no NDEATH. First a DDEATH for each device removed that was born, then the
NBIRTH (seq 0, the node metrics of the buses now) and a DBIRTH for each device online
in the new set; a device added is born when it first answers. A metric kept (of a
device kept, or a bus's) keeps its alias; a new metric takes a number no other
metric of the process has had. While the node is not born (the broker away, the
primary host offline), the reload changes only the device set: the next births carry
it. A change of the `mqtt` section itself (the broker, the `sparkplug` settings)
restarts the Sparkplug client instead: an NDEATH, a new connection, the next bdSeq.

## Primary host

With `primary_host_id`, the node subscribes to `{ns}/STATE/{{primary_host_id}}` (the
Sparkplug 3.0 JSON `{{"online": true, "timestamp": …}}`) and then to 2.2's
`STATE/{{primary_host_id}}` (`ONLINE`/`OFFLINE`), and is born only while the host
says online. Each connection waits for a STATE of its own (a retained one comes at
once). When the host says offline, the node sends its NDEATH, disconnects, and
connects again (a new bdSeq), to be born when the host is back. Which STATE counts:

- **Older is ignored.** A 3.0 STATE whose `timestamp` is older than the newest one
  the node has taken is ignored (and counted, and logged), online or offline: it is
  a will or a retained message of an earlier host session, delivered late (Sparkplug
  3.0: `message-flow-edge-node-birth-publish-phid-wait-timestamp`,
  `operational-behavior-edge-node-termination-host-offline-timestamp`). An equal
  timestamp is taken: a 3.0 host's will carries the timestamp of the birth it ends.
  A STATE without a timestamp is taken as it comes.
- **The 3.0 topic wins.** Once the host has published on `{ns}/STATE/…` (as seen by
  this gateway since it started), its 2.2 topic is ignored: a host that moved to 3.0
  often leaves an `OFFLINE` retained there for good. The 2.2 topic counts only while
  no 3.0 STATE was ever seen. The 3.0 topic is subscribed first, so its retained
  STATE is read before a retained 2.2 one.
- **No flapping.** A STATE that asks for a birth within {hold:g} s of the last birth
  waits until then, and the births are made if the host still says online. An
  offline is acted on at once.
"""


#: (message, topic after ``{ns}/{group}/``, when, what it carries): one row each.
MESSAGES = (
    ("NBIRTH", "NBIRTH/{gateway_id}",
     "after each connect (once the primary host is online), on a rebirth, and after "
     "a reload that changed the sensors",
     f"seq 0; `{BDSEQ}` (Int64, this connection's), `{REBIRTH}` (Boolean, false), "
     "the node metrics below"),
    ("DBIRTH", "DBIRTH/{gateway_id}/{sensor}",
     "after the NBIRTH for each sensor that is online; when a sensor answers again",
     "every metric of the device below: name, alias, datatype, value, the sample's time; "
     "measured values with an `engUnit` property"),
    ("DDATA", "DDATA/{gateway_id}/{sensor}", "each new reading, status or counter change; "
     "each alarm transition, in a DDATA of its own",
     "only the metrics that changed, by alias (with their datatype: Tahu's decoder needs "
     "it), stamped with the sample's wire time (an alarm's, with its transition's time)"),
    ("DDEATH", "DDEATH/{gateway_id}/{sensor}",
     "the sensor went offline; a reload removed it (before the NBIRTH)", "seq only"),
    ("NDATA", "NDATA/{gateway_id}", "a bus's counters changed (checked every few seconds)",
     "the node metrics that changed, by alias"),
    ("NDEATH", "NDEATH/{gateway_id}",
     "the will of the session (QoS 1); or sent on a clean stop, or when the primary host "
     "goes offline", f"`{BDSEQ}` equal to the NBIRTH's; no seq"),
)


def _messages() -> str:
    rows = [f"| `{NAMESPACE}/{{group}}/{topic}` | {when} | {what} |"
            for _, topic, when, what in MESSAGES]
    return "\n".join(["| topic | when | content |", "|---|---|---|", *rows])


def _device_table(series: Series, protocol: WireProtocol) -> list[str]:
    sensor = SensorConfig(name="boom", series=series, address=0)
    rows = [*STATUS_ROWS, *identity_rows(sensor, protocol)]
    return [f"| `{r.name}` | {r.datatype.spelled} | {r.description} |" for r in rows]


ALARMS = """## Alarms

Each alarm of a sensor ([alarms.md](alarms.md)), its built-in `communication` alarm
last, is a folder of its device's metrics, `Alarms/{{alarm}}/…`, in the DBIRTH (every
alarm, with its state at that moment):

{table}

- **Each transition is a DDATA of its own**, sent as the gateway makes it (raised
  after its on-delay, cleared through its hysteresis after its off-delay,
  acknowledged), with the alarm's metrics that changed (`State` always, `Active`
  and/or `Acked`), each stamped with the transition's time. Not merged with a
  reading's DDATA nor with another transition: a host sees every transition, even
  a raise and its acknowledgement in the same millisecond. A reading that raises an
  alarm comes first, in its own DDATA.
- **A device that is not born** (offline: after its DDEATH; or while the node waits
  for its primary host, or for the broker) gets no DDATA: its next DBIRTH carries
  the states then. So a sensor that goes offline has its DDEATH, and its
  `communication` alarm, raised after it, is in the DBIRTH when the sensor answers
  again, still active: it clears at the gateway's next staleness check (within
  0.1 s), and that transition follows in a DDATA (`rtn_unacked` until acknowledged).
  A sensor that is only stale is still born: its `communication` alarm goes out in
  DDATA like the others.
- **Acknowledging** (with `allow_commands: true`, as the commands are): a DCMD
  writing `Alarms/{{alarm}}/Acked` = true (Boolean). The DDATA of the transition comes
  first, then the answer in `Commands/Result`: `Alarms/{{alarm}}/Acked: ok`, or
  `Alarms/{{alarm}}/Acked: nothing_to_acknowledge: boom/boom_lean is acknowledged
  already: nothing to acknowledge` (also for an alarm that is `normal`). False, no
  value or another datatype is refused with `bad_arguments`, and acknowledges nothing.
  The journal records the acknowledgement `by` `"{by}"` (the broker does not say who
  published the DCMD). With `allow_commands: false` such a DCMD is ignored, counted
  and logged like any command, and the alarm stays unacknowledged: give the
  operator's right to acknowledge only with the right to run commands.
"""


def _alarm_table() -> str:
    rows = [f"| `{row.metric('{alarm}')}` | {row.datatype.spelled} | {row.description} |"
            for row in ALARM_ROWS]
    return "\n".join(["| metric | datatype | what it says |", "|---|---|---|", *rows])


def markdown() -> str:
    intro = INTRO.format(ns=NAMESPACE, bdseq=BDSEQ, rebirth=REBIRTH, messages=_messages(),
                         hold=REBIRTH_HOLD_S)
    lines = [intro, "## Node metrics", "",
             f"Besides `{BDSEQ}` and `{REBIRTH}`, the NBIRTH carries each bus's counters "
             "(the `buses` of the configuration, by name); an NDATA carries those that "
             f"changed, at most every {NODE_DATA_EVERY_S:g} s:", "",
             "| metric | datatype | what it says |", "|---|---|---|",
             *(f"| `{row.metric('{bus}')}` | {row.datatype.spelled} | {row.description} |"
               for row in BUS_ROWS), ""]
    lines += ["## Device metrics",
             "", "The measured values, one folder per value group; only the groups a "
             "series measures are in its births, and the groups derived from them (Tilt, "
             "Vibration: [alarms.md](alarms.md#derived-values)). Double, as the sensor "
             "gave them (32.52, not a float32's 32.52000045776367); a value that has none "
             "now (the vibration before a second of ten samples, the direction of no "
             "tilt) is null:", "",
             "| metric | datatype | engUnit | series |", "|---|---|---|---|"]
    for group, spec in VALUE_GROUPS.items():
        who = ", ".join(s.name for s in Series if group in CAPABILITIES[s].groups)
        for name in spec.fields:
            lines.append(f"| `{spec.title}/{name}` | {VALUE_TYPE.spelled} | "
                         f"{spec.symbol or '(none)'} | "
                         f"{who} |")
    lines += ["", "Status and identity, every series:", "",
              "| metric | datatype | what it says |", "|---|---|---|",
              *_device_table(Series.AH, WireProtocol.NATIVE), "",
              "Commands, with `allow_commands: true`: the catalogue's, for the series and "
              "protocol that have them, and their outcome:", "",
              "| metric | datatype | series (native / Modbus RTU) | what it does |",
              "|---|---|---|---|"]
    for command in CATALOGUE.values():
        where = []
        for protocol in WireProtocol:
            have = [s.name for s in Series
                    if any(r.command == command.name for r in command_rows(s, protocol))]
            where.append(", ".join(have) or "none")
        lines.append(f"| `Commands/{command.name}` | {command_type(command).spelled} | "
                     f"{' / '.join(where)} | {command.summary} |")
    lines += [f"| `Commands/Result` | {DataType.STRING.spelled} | all | the outcome of "
              "the last command written as a DCMD |", ""]
    lines += [ALARMS.format(table=_alarm_table(), by=ACK_BY)]
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown(), end="")
