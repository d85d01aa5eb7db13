"""The one exception base of the sensor agent, and the errors that are not the codec's own."""

from __future__ import annotations


class SensorAgentError(Exception):
    """Base class of every error raised by `sensor_agent`."""


class DriverError(SensorAgentError):
    """The device cannot be opened, or does not answer like a SCIP 2.0 laser."""


class SourceError(SensorAgentError):
    """A scan source cannot be started (missing log file, unsupported format, ...)."""


class EmulatorError(SensorAgentError):
    """The emulator cannot create its pty, symlink or TCP listener."""
