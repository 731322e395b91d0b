"""canbrake's user-facing error types (small hierarchy, as python-can's CanError family)."""
from __future__ import annotations


class CanbrakeError(Exception):
    """Base class of canbrake's errors."""


class InputError(CanbrakeError):
    """Bad input from the user: printed as one line, exit status 2."""


class ScenarioError(CanbrakeError):
    """A scenario cannot be used; the message names the file and the field (printed as one line,
    exit status 2). Defined here, below every layer, so that bus/ can raise it without importing
    :mod:`canbrake.scenario` (re-exported there)."""
