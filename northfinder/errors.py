"""Exceptions that carry a message meant for the user (the CLI prints them as one line).

Anything raised as a :class:`NorthfinderError` is a user-facing condition: a bad input, a
port that does not answer, a device in the wrong state. Anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations


class NorthfinderError(Exception):
    """Base of every error the CLI reports as one line with a non-zero exit code."""

    exit_code = 2


class InputError(NorthfinderError, ValueError):
    """Estimator or CLI input that cannot give a meaningful result (n < 3, NaN, tilt too big…)."""


class ConfigError(NorthfinderError):
    """A malformed or out-of-range configuration value; the message names the key and the range."""


class DeviceError(NorthfinderError):
    """A device did not answer, answered wrongly, or refused a command.

    `device` is a short name ("turntable", "imu", "accelerometer", "gnss"); `port` the URL or
    channel it was opened on. The message says what to do where that is known.
    """

    exit_code = 3

    def __init__(self, device: str, port: str | None, message: str):
        self.device = device
        self.port = port
        where = f"{device} on {port}" if port else device
        super().__init__(f"{where}: {message}")


class RunDamaged(NorthfinderError):
    """A run directory whose files are damaged (a raw log cut short, an event that cannot be
    decoded): exits 4, unlike a usage error (2), so scripts can tell the two apart."""

    exit_code = 4


class RunAborted(NorthfinderError):
    """The run was stopped (Ctrl-C / SIGTERM); the data measured so far has been saved."""

    exit_code = 130
