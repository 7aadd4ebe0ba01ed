"""The protocol layer's exceptions, in one tree.

Two kinds of trouble are kept apart on purpose:

* ``FrameError``: the *peer* sent something we cannot accept (bad checksum, a BCD
  nibble above 9, a frame shape no document describes).  On a noisy RS-485 line this
  is routine, so callers count it and carry on.
* ``UsageError``: *our own* caller asked for something impossible (an angle of 1000°,
  a baud rate the sensor does not know).  It is a bug or a bad user input upstream and
  is also a ``ValueError`` so generic validation code catches it.

Library errors (pymodbus) are converted to these in one place, ``modbus_rtu``.
"""

from __future__ import annotations

from ..errors import GatewayError


class ProtocolError(GatewayError):
    """Base of everything the protocol layer raises (a branch of ``imu_gateway.errors``'s
    tree)."""


class FrameError(ProtocolError):
    """The bytes on the wire do not form an acceptable frame."""


class BadChecksum(FrameError):
    """Native sum checksum or Modbus CRC mismatch."""


class BadLength(FrameError):
    """A frame is shorter or longer than its header or its shape says."""


class BadBcd(FrameError):
    """A packed-BCD field holds a nibble above 9 or a sign nibble other than 0/1."""


class UnknownFrame(FrameError):
    """A well-formed frame whose command/length (or function code) no document describes."""


class UsageError(ProtocolError, ValueError):
    """The caller asked for a frame or value the protocol cannot express."""
