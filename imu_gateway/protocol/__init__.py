"""Sans-IO protocol code: no asyncio, no serial port, no clock."""
