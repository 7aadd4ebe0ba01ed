"""OPC UA (docs/opcua.md): the gateway's address space for SCADA and MES clients."""
