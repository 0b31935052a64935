"""The simulator's errors: one home, imported by every layer."""
from __future__ import annotations

from typing import Any


class ConfigError(ValueError):
    """A setting is missing, of the wrong type or out of its allowed range.

    ``field`` is the dotted path of the setting (``laser.pulse_energy_j``), ``value`` what was given and
    ``allowed`` a human-readable statement of what is accepted.
    """

    def __init__(self, field_path: str, value: Any, allowed: str):
        self.field = field_path
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field_path} = {value!r} is not allowed: {allowed}")


class Cancelled(Exception):
    """The run was cancelled by the caller; nothing was written."""
