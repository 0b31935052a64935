"""The simulator's errors: one home, imported by every layer."""
from __future__ import annotations

import reprlib
from typing import Any

#: Longest echo of a bad value (or field path) in an error message: a 100 MB value gives a one-line error.
MAX_ECHO_CHARS = 120
_ECHO = reprlib.Repr()
_ECHO.maxstring = _ECHO.maxother = _ECHO.maxlong = MAX_ECHO_CHARS
_ECHO.maxlevel, _ECHO.maxlist, _ECHO.maxtuple, _ECHO.maxdict = 3, 8, 8, 8


def cut(text: str, n: int) -> str:
    """``text`` on one line, cut to about ``n`` characters (with its length when cut)."""
    text = text.replace("\n", "\\n")
    return text if len(text) <= n else f"{text[:n - 25]}… ({len(text)} characters)"


def echo(value) -> str:
    """``repr(value)`` cut to about :data:`MAX_ECHO_CHARS` characters and 3 levels of nesting, on one line
    (never fails: an integer too long to print becomes its digit count)."""
    try:
        text = _ECHO.repr(value)
    except (ValueError, RecursionError, TypeError):  # e.g. ints beyond sys.get_int_max_str_digits()
        text = (f"<an integer of about {int(value.bit_length() * 0.30103) + 1} digits>"
                if isinstance(value, int) else f"<a {type(value).__name__}>")
    return cut(text, MAX_ECHO_CHARS + 30)


class ConfigError(ValueError):
    """A setting is missing, of the wrong type or out of its allowed range.

    ``field`` is the dotted path of the setting (``laser.pulse_energy_j``), ``value`` what was given and
    ``allowed`` a human-readable statement of what is accepted.
    """

    def __init__(self, field_path: str, value: Any, allowed: str):
        self.field = field_path
        self.value = value
        self.allowed = allowed
        super().__init__(f"{cut(str(field_path), MAX_ECHO_CHARS)} = {echo(value)} is not allowed: "
                         f"{cut(str(allowed), 4 * MAX_ECHO_CHARS)}")


class Cancelled(Exception):
    """The run was cancelled by the caller; nothing was written."""
