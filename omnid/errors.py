"""The omnid exception tree.

Every error omnid raises on purpose derives from :class:`OmnidError`, and also from the
built-in exception a caller would naturally catch::

    OmnidError
     +-- ConfigError(ValueError)        a configuration file or value is wrong (names the key)
     +-- InputError(ValueError)         a user-supplied file or array is unusable (names it)
     +-- CalibrationError(ValueError)   a calibration capture cannot give a valid calibration
     +-- ProtocolError(ValueError)      a frame failed its checksum/CRC or is malformed
     +-- DeviceError(OSError)           a device link failed (open, read, write)
          +-- DeviceTimeout(TimeoutError) a device did not answer within its deadline
          +-- DeviceClosed              the device is not open (never opened, or unplugged)

Driver errors are re-raised ``from`` their cause so the original OS error stays visible.
"""

from __future__ import annotations


class OmnidError(Exception):
    """Root of all errors omnid raises on purpose."""


class ConfigError(OmnidError, ValueError):
    """A configuration file or value is wrong; the message names the key (e.g. ``safety.stop_distance_mm``)."""


class InputError(OmnidError, ValueError):
    """A user-supplied input (image file, array) is unusable; the message names it."""


class CalibrationError(OmnidError, ValueError):
    """A calibration capture cannot give a valid calibration; the message gives residuals."""


class ProtocolError(OmnidError, ValueError):
    """A frame failed its checksum/CRC, or is malformed."""


class DeviceError(OmnidError, OSError):
    """A device link failed: open, read or write."""


class DeviceTimeout(DeviceError, TimeoutError):
    """A device did not answer within its deadline."""


class DeviceClosed(DeviceError):
    """The device is not open (never opened, closed, or unplugged)."""
