"""Typed SCIP 2.0 errors: one base (`ScipError`) and a subclass per kind of failure.

Status codes are mapped with `status_error(command_name, status)`. The table follows the
SCIP 2.0 specification (Hokuyo C-42-03320B) with the later SCIP 2.x meanings of `0L`/`0M`/`10`
used by the UTM-30LX-EW and UST firmware (see docs PROTOCOLS.md A.6).
"""

from __future__ import annotations

from typing import Final

from sensor_agent.errors import SensorAgentError


class ScipError(SensorAgentError):
    """Base class of every error produced by the SCIP codec."""


class CommandError(ScipError, ValueError):
    """A command that cannot be built (parameter out of range, bad string characters)."""


class ChecksumError(ScipError):
    """A line whose checksum character does not match its content."""

    def __init__(self, line: bytes) -> None:
        super().__init__(f"checksum mismatch on line {line[:72]!r}")
        self.line = line


class MalformedReplyError(ScipError):
    """A reply whose shape is wrong: missing lines, wrong lengths, characters outside 0x30-0x6F."""


class StatusError(ScipError):
    """The device answered with a status other than success."""

    def __init__(self, command: str, status: str, meaning: str) -> None:
        super().__init__(f"{command}: status {status!r} ({meaning})")
        self.command = command
        self.status = status
        self.meaning = meaning


class CommandRejectedError(StatusError):
    """The device did not understand the command (`0A`-`0H`): a host-side bug or line noise."""


class UndefinedCommandError(CommandRejectedError):
    """`0E`: undefined command (also what garbage on the line gets back)."""


class ParameterError(StatusError):
    """A numeric parameter of the command was rejected (`01`-`07` for GD/MD/ME, `01` for TM)."""


class DeviceStateError(StatusError):
    """The command is not allowed in the device's current state (`10`, `0I`, `0L`, TM `02`-`04`)."""


class LaserOffError(DeviceStateError):
    """GD/MD/ME `10`: the laser is off (send BM first)."""


class HardwareError(StatusError):
    """The device reports a laser or motor problem (`21`-`97`, BM `01`)."""


# Statuses every command can return (SCIP 2.0 p.23 plus later 2.x firmware).
_GENERIC: Final[dict[str, tuple[type[StatusError], str]]] = {
    "0A": (CommandRejectedError, "unable to create transmission data"),
    "0B": (CommandRejectedError, "buffer shortage or command already processed"),
    "0C": (CommandRejectedError, "command with insufficient parameters"),
    "0D": (CommandRejectedError, "undefined command or command too long"),
    "0E": (UndefinedCommandError, "undefined command"),
    "0F": (CommandRejectedError, "command with insufficient parameters or not supported"),
    "0G": (CommandRejectedError, "string characters exceed 16 letters"),
    "0H": (CommandRejectedError, "string characters have invalid letters"),
    "0I": (DeviceStateError, "sensor is in firmware update mode"),
    "0L": (DeviceStateError, "sensor is in an abnormal state"),
    "0M": (DeviceStateError, "measurement is unstable"),
    "10": (DeviceStateError, "command denied in the current state"),
}

_SCAN: Final[dict[str, tuple[type[StatusError], str]]] = {
    "01": (ParameterError, "start step has non-numeric value"),
    "02": (ParameterError, "end step has non-numeric value"),
    "03": (ParameterError, "cluster count has non-numeric value"),
    "04": (ParameterError, "end step is out of range"),
    "05": (ParameterError, "end step is smaller than start step"),
    "06": (ParameterError, "scan interval has non-numeric value"),
    "07": (ParameterError, "number of scans has non-numeric value"),
    "10": (LaserOffError, "laser is off"),
    "98": (DeviceStateError, "resumed after confirming normal laser operation"),
}

_BY_COMMAND: Final[dict[str, dict[str, tuple[type[StatusError], str]]]] = {
    "GD": _SCAN,
    "MD": _SCAN,
    "ME": _SCAN,
    "BM": {"01": (HardwareError, "unable to control due to laser malfunction")},
    "TM": {
        "01": (ParameterError, "invalid control code"),
        "02": (DeviceStateError, "already in time adjust mode"),
        "03": (DeviceStateError, "not in time adjust mode (TM2)"),
        "04": (DeviceStateError, "not in time adjust mode (TM1)"),
    },
}

# Statuses that mean success for a given command, besides "00".
SUCCESS_STATUSES: Final[dict[str, frozenset[str]]] = {
    "BM": frozenset({"00", "02"}),  # "02" = laser already on; urg_c treats it as success too
}


def is_success(command_name: str, status: str) -> bool:
    return status == "00" or status in SUCCESS_STATUSES.get(command_name, frozenset())


def status_error(command_name: str, status: str) -> StatusError:
    """The typed error for a non-success `status` answered to `command_name` (e.g. "MD", "TM")."""
    family = command_name[:2]
    specific = _BY_COMMAND.get(family, {})
    if status in specific:
        cls, meaning = specific[status]
    elif status in _GENERIC:
        cls, meaning = _GENERIC[status]
    # ASCII digits only: str.isdigit() also accepts '¹' and the like, which int() refuses
    # (garbage on the line, found by the fuzz test).
    elif status.isascii() and status.isdigit() and 21 <= int(status) <= 49:
        cls, meaning = HardwareError, "processing stopped to verify the error"
    elif status.isascii() and status.isdigit() and 50 <= int(status) <= 97:
        cls, meaning = HardwareError, "hardware trouble (laser, motor or scan speed)"
    else:
        cls, meaning = StatusError, "unknown status"
    return cls(command_name, status, meaning)


__all__ = [
    "SUCCESS_STATUSES",
    "ChecksumError",
    "CommandError",
    "CommandRejectedError",
    "DeviceStateError",
    "HardwareError",
    "LaserOffError",
    "MalformedReplyError",
    "ParameterError",
    "ScipError",
    "StatusError",
    "UndefinedCommandError",
    "is_success",
    "status_error",
]
