"""The MQTT transport that both MQTT front ends share: plain topics (``frontends/mqtt``)
and Sparkplug B (``frontends/sparkplug``).

* ``session``: one connection kept up across brokers and reconnects;
* ``driver``: paho's network loop on the gateway's event loop (no thread of paho's);
* ``pipe``: the way to paho: the outbox, the control messages, the in-flight window;
* ``failover``: which broker of ``mqtt.url`` is next, and the back-off;
* ``probe``: a connection of its own that reads retained messages before a connect;
* ``message``: what is carried (``Message``) and counted (``Counters``);
* ``errors``: its branch of the error tree (``BrokerUnreached``, ``ProbeFailed``).

It imports the config, the error tree, ``supervise`` and paho; no front end, cache,
command or bus code (tests/test_layering.py).
"""
