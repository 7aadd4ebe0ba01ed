"""The Prometheus metrics, collected from the gateway's stats at each scrape."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from ... import __version__
from ...cache import Status
from ...stats import ERROR_KINDS
from ..common import GatewayLike

# ------------------------------------------------------------------ metrics


MQTT_COUNTERS = (  # the MQTT client's own: metric, its key in MqttClient.stats(), help
    ("mqtt_connects", "connects", "connections made to the broker"),
    ("mqtt_commands", "commands", "command messages received"),
    ("mqtt_command_errors", "command_errors", "commands that ended in an error result"),
)
HTTP_COUNTERS = (  # the HTTP server's own: metric, its key in HttpServer.stats(), help
    ("http_request_timeouts", "request_timeouts",
     "connections closed: a request's headers or body did not come in time"),
    ("http_streams_dropped", "dropped_streams", "stream clients dropped: their socket "
     "stayed full"),
    ("http_stream_events_skipped", "skipped_events", "events skipped for stream clients "
     "behind, the oldest first"),
)

CAPTURE_COUNTERS = (  # event capture's (docs/alarms.md, "Captures"): metric, key, help
    ("capture_triggers", "triggers", "capture triggers (manual and alarms)"),
    ("capture_written", "written", "captures written"),
    ("capture_failures", "failed", "captures not written, or a capture folder not made: "
     "a full or read-only disk"),
)


#: makes a metric family and collects it: (its class, name, help, labels)
Family = Callable[[type[GaugeMetricFamily] | type[CounterMetricFamily], str, str, list[str]], Any]


class GatewayCollector:
    """Prometheus metrics, read from the gateway's stats at each scrape."""

    def __init__(self, gateway: GatewayLike) -> None:
        self.gateway = gateway

    def collect(self) -> list[Metric]:
        out: list[Metric] = []

        def family(kind: type[GaugeMetricFamily] | type[CounterMetricFamily], name: str,
                   doc: str, labels: list[str]) -> Any:
            metric = kind("imu_gateway_" + name, doc, labels=labels)
            out.append(metric)
            return metric

        # the usual "info" gauge: 1, its labels say what runs
        family(GaugeMetricFamily, "build_info", "the running imu-gateway's version",
               ["version"]).add_metric([__version__], 1)
        self._buses(family)
        self._sensors(family)
        self._frontends(family)
        self._alarms(family)
        self._captures(family)
        return out

    def _alarms(self, family: Family) -> None:
        active = family(GaugeMetricFamily, "alarm_active", "1 while the alarm is active",
                        ["sensor", "alarm", "severity"])
        moved = family(CounterMetricFamily, "alarm_transitions", "changes of the alarm's "
                       "state since start (acknowledgements too)", ["sensor", "alarm"])
        counts = self.gateway.alarm_counts()
        for state in self.gateway.alarm_states():
            active.add_metric([state.sensor, state.name, state.severity.value],
                              1.0 if state.active else 0.0)
            moved.add_metric([state.sensor, state.name],
                             counts.transitions.get((state.sensor, state.name), 0))
        family(CounterMetricFamily, "alarm_journal_errors", "transitions the journal's file "
               "could not take (a full or read-only disk)", []).add_metric(
                   [], counts.journal_errors)


    def _captures(self, family: Family) -> None:
        captures = self.gateway.captures
        if captures is None:
            return
        for name, key, doc in CAPTURE_COUNTERS:
            family(CounterMetricFamily, name, doc, []).add_metric([], captures.counts[key])

    def _buses(self, family: Family) -> None:
        tx = family(CounterMetricFamily, "bus_transactions", "exchanges on the line", ["bus"])
        errors = family(CounterMetricFamily, "bus_errors", "failed exchanges by kind",
                        ["bus", "kind"])
        util = family(GaugeMetricFamily, "bus_utilisation",
                      "time in exchanges / elapsed time", ["bus"])
        queue = family(GaugeMetricFamily, "bus_queue_depth", "jobs waiting for the line",
                       ["bus"])
        port = family(GaugeMetricFamily, "bus_port_open", "1 when the port is open", ["bus"])
        late = family(CounterMetricFamily, "bus_late_writes", "requests written too late "
                      "to end before a stream's next frame", ["bus"])
        for bus in self.gateway.stats():
            tx.add_metric([bus.name], bus.transactions)
            late.add_metric([bus.name], bus.late_writes)
            for kind in dict.fromkeys([*ERROR_KINDS, *bus.errors]):  # every kind, from 0
                errors.add_metric([bus.name, kind], bus.errors.get(kind, 0))
            util.add_metric([bus.name], bus.utilisation)
            queue.add_metric([bus.name], bus.queue_depth)
            port.add_metric([bus.name], 1.0 if bus.port_open else 0.0)

    def _sensors(self, family: Family) -> None:
        g = self.gateway
        rate = family(GaugeMetricFamily, "sensor_rate_hz", "readings per second", ["sensor"])
        age = family(GaugeMetricFamily, "sensor_age_seconds", "age of the latest reading",
                     ["sensor"])
        status = family(GaugeMetricFamily, "sensor_status", "1 for the sensor's status",
                        ["sensor", "status"])
        readings = family(CounterMetricFamily, "sensor_readings", "readings received",
                          ["sensor"])
        sensor_errors = family(CounterMetricFamily, "sensor_errors", "timeouts and bad frames",
                               ["sensor"])
        latency = family(GaugeMetricFamily, "sensor_latency_seconds", "smoothed answer "
                         "latency (the sensor's turnaround plus the adapter's)", ["sensor"])
        timeout = family(GaugeMetricFamily, "sensor_timeout_seconds", "answer timeout beyond "
                         "the wire time, learned from the latency", ["sensor"])
        late = family(CounterMetricFamily, "sensor_late_answers", "answers after their "
                      "timeout, used", ["sensor"])
        early = family(CounterMetricFamily, "sensor_early_answers", "answers sooner than "
                       "request, RTU gap and answer could cross the wire, used", ["sensor"])
        stops = family(CounterMetricFamily, "sensor_stream_stops", "stops sent to a sensor "
                       "found streaming unasked", ["sensor"])
        for snap in g.cache.snapshots():
            stats = g.sensor_stats(snap.name)
            rate.add_metric([snap.name], stats.achieved_hz)
            if stats.latency_ms is not None:
                latency.add_metric([snap.name], stats.latency_ms / 1000)
            timeout.add_metric([snap.name], stats.timeout_ms / 1000)
            late.add_metric([snap.name], stats.late_answers)
            early.add_metric([snap.name], stats.early_answers)
            stops.add_metric([snap.name], stats.stream_stops)
            if snap.age_ms is not None:
                age.add_metric([snap.name], snap.age_ms / 1000)
            for s in Status:
                status.add_metric([snap.name, s.value], 1.0 if snap.status is s else 0.0)
            readings.add_metric([snap.name], snap.seq)
            sensor_errors.add_metric([snap.name], snap.errors)

    def _frontends(self, family: Family) -> None:
        clients = family(GaugeMetricFamily, "frontend_clients", "connected clients",
                         ["frontend"])
        requests = family(CounterMetricFamily, "frontend_requests", "requests served",
                          ["frontend"])
        restarts = family(CounterMetricFamily, "frontend_restarts", "restarts after a "
                          "failure (docs/reliability.md)", ["frontend"])
        frontends = self.gateway.frontend_stats()
        for name, served in frontends.items():
            restarts.add_metric([name], served["restarts"])
            if "clients" in served:  # the servers (the MQTT client has its own below)
                clients.add_metric([name], served["clients"])
                requests.add_metric([name], served["requests"])
        for name, key, doc in HTTP_COUNTERS if "http" in frontends else ():
            family(CounterMetricFamily, name, doc, []).add_metric([], frontends["http"][key])
        mqtt = frontends.get("mqtt")
        if mqtt is not None:
            family(GaugeMetricFamily, "mqtt_connected", "1 when connected to the broker",
                   []).add_metric([], 1.0 if mqtt["connected"] else 0.0)
            family(CounterMetricFamily, "mqtt_published", "messages handed to the client",
                   []).add_metric([], mqtt["published"])
            family(CounterMetricFamily, "mqtt_dropped", "messages dropped while the broker "
                   "was away", []).add_metric([], mqtt["dropped"])
            for name, key, doc in MQTT_COUNTERS:
                family(CounterMetricFamily, name, doc, []).add_metric([], mqtt[key])
            family(GaugeMetricFamily, "mqtt_queue_depth", "messages waiting for the broker",
                   []).add_metric([], mqtt["queued"])
