"""The exception tree of racecar-hw.

::

    RacecarError
    ├── ConfigError            a bad key or value in the configuration
    ├── DeviceError
    │   ├── DeviceNotFound     no device at the path, address or USB id
    │   ├── DeviceIOError      the device went away or an OS call failed
    │   └── DeviceTimeout      the device did not answer in time (also a TimeoutError)
    ├── ProtocolError
    │   ├── RemoteProtocolError  the peer sent something the protocol forbids
    │   └── LocalProtocolError   the caller asked for something the protocol cannot say
    ├── TopicTypeError         a message of the wrong type on a bus topic
    └── BagError               a bag that cannot be read or written as asked
        └── BagWriteError      a bag (or a recovered copy) that cannot be written: the disk's
                               fault or the folder's, not the data's

Drivers translate pyserial and OS errors at their boundary with ``raise ... from err``.
"""

from __future__ import annotations


class RacecarError(Exception):
    """Base class of every error racecar-hw raises on purpose."""


class ConfigError(RacecarError):
    """A configuration key or value is wrong; the message names the key."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


class DeviceError(RacecarError):
    """A hardware device could not be used."""


class DeviceNotFound(DeviceError):
    """No device at the configured path, address or USB id."""


class DeviceIOError(DeviceError):
    """The device went away (unplugged, connection dropped) or an OS call failed."""


class DeviceTimeout(DeviceError, TimeoutError):
    """The device did not answer within the deadline."""


class ProtocolError(RacecarError):
    """A wire-protocol rule was broken."""


class RemoteProtocolError(ProtocolError):
    """The peer sent bytes the protocol forbids."""


class LocalProtocolError(ProtocolError):
    """The caller asked to encode something the protocol cannot express."""


class TopicTypeError(RacecarError, TypeError):
    """A message was published on a topic that carries another type."""


class BagError(RacecarError):
    """A bag is missing, malformed, or lacks what was asked of it."""


class BagWriteError(BagError):
    """A bag being written (recorded, or the output of a recovery) cannot be: the disk is full, the
    file was deleted or moved while it was written. The message names the file written, never the
    bag read (which is fine)."""
