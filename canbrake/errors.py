"""canbrake's user-facing error types (small hierarchy, as python-can's CanError family)."""
from __future__ import annotations


class CanbrakeError(Exception):
    """Base class of canbrake's errors."""


class InputError(CanbrakeError):
    """Bad input from the user: printed as one line, exit status 2."""
