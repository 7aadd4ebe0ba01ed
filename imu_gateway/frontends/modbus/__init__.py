"""The Modbus TCP front end (docs/modbus-tcp.md): ``server.ModbusTcpServer`` answers from
the register map (``map``, docs/register-map.md), with the device identification of
``ident`` and Modbus/TCP Security in ``tls``."""
