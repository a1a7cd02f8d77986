"""The exceptions that reach the user as a one-line ``Error: ...`` and an exit code (README, "Exit codes").

Imports no numpy: ``condtrack --help`` loads this module (tests/test_startup.py).
"""

import errno
import warnings
from pathlib import PurePath


class CondtrackError(Exception):
    """Bad input or configuration: the message names the file, key or frame.

    The command line prints ``Error: <message>`` on stderr and exits with
    ``exit_code`` (1: the run failed), without a traceback and without leaving
    a partial output file.
    """

    exit_code = 1


class MissingInput(CondtrackError):
    """An input path given on the command line does not exist: a usage error, exit code 2 (as Click's)."""

    exit_code = 2


class CondtrackWarning(UserWarning):
    """Something the user should know that does not stop the run (a skipped file, a setting with no effect).

    The command line prints each as a ``warning: ...`` line (none with ``track -q``);
    in Python it is a normal warning: ``warnings.simplefilter("error", CondtrackWarning)`` makes it an exception.
    """


def warn(message: str) -> None:
    """Issue ``message`` as a :class:`CondtrackWarning`."""
    warnings.warn(message, CondtrackWarning, stacklevel=2)
class InvalidArgument(CondtrackError, ValueError):
    """A Python API argument with a wrong value (seed=-1); the message is the command line's for the same value."""

    exit_code = 2


class InvalidArgumentType(CondtrackError, TypeError):
    """A Python API argument of a wrong type (seed=1.5, an array of strings)."""

    exit_code = 2


def names_input(message: str, name: str) -> bool:
    """Whether ``message`` begins with the input ``name`` and a colon, as typed or as its reader names it
    (``x/frames`` for ``./x/frames/``): a batch then does not name it again."""
    return message.startswith((f"{name}:", f"{PurePath(name)}:"))


def read_error(error: OSError | Exception, message: str) -> CondtrackError:
    """``message`` as :class:`MissingInput` when ``error`` says the file does not exist, else as CondtrackError."""
    return (MissingInput if isinstance(error, FileNotFoundError) else CondtrackError)(message)


def write_error(path: object, error: OSError) -> CondtrackError:
    """``<path>: no space left on device`` for a full disk, else ``<path>: cannot write (<reason>)``."""
    if error.errno == errno.ENOSPC:
        return CondtrackError(f"{path}: no space left on device")
    return CondtrackError(f"{path}: cannot write ({error.strerror or error})")


def counted(count: int, noun: str) -> str:
    """``'1 frame'``, ``'2 frames'``: ``count`` and ``noun``, plural unless ``count`` is 1."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def plain(value: object) -> str:
    """``value`` for a message, as Python shows it: numpy scalars and arrays (also inside lists, tuples and dicts) as
    the plain values they hold, ``'abc'`` and ``3`` rather than ``np.str_('abc')`` and ``np.int64(3)``."""
    return repr(python_value(value))


def python_value(value: object) -> object:
    """``value`` with every numpy scalar or array in it (also inside lists, tuples and dicts) as the plain Python
    values it holds."""
    if type(value).__module__ == "numpy":  # a numpy scalar or array, recognised without importing numpy
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return type(value)(python_value(item) for item in value)
    if isinstance(value, dict):
        return {python_value(key): python_value(item) for key, item in value.items()}
    return value
