"""The front ends, one package each: ``modbus`` (Modbus TCP), ``mqtt`` (plain topics and
Home Assistant), ``sparkplug`` (Sparkplug B), ``opcua`` and ``rest`` (REST, the live
stream and the dashboard).  They read the cache and ask the gateway for commands; they
never import ``protocol`` or ``bus``.  Of their siblings they use only ``common.py``,
and the MQTT ones the transport they share, ``imu_gateway.mqtt_link``."""
