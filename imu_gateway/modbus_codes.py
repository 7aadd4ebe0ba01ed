"""Modbus's numbers that both sides of the gateway speak: the function codes it uses
(to the sensors over RTU, to PLCs over TCP) and the exception codes (Modbus
Application Protocol v1.1b3, 6 and 7).  A leaf: it imports nothing, and the protocol
layer and the front ends may both import it."""

from __future__ import annotations

READ_HOLDING, READ_INPUT, WRITE_SINGLE, WRITE_MULTIPLE = 3, 4, 6, 16

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 0x01, 0x02, 0x03, 0x04
DEVICE_BUSY, GATEWAY_PATH, TARGET_FAILED = 0x06, 0x0A, 0x0B
