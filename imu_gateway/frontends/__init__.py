"""The front ends: Modbus TCP, MQTT, REST.  They read the cache and ask the gateway
for commands; they never import ``protocol`` or ``bus``, nor each other."""
