"""The exception tree of the ``occ`` package.

::

    OCCError                      anything the daemon core raises on purpose
     +-- ConfigError              a configuration file is invalid (names file, line, field path)
     +-- StateError               a request not allowed in the current state (e.g. Run while FAULT)
     +-- DriverError              hardware I/O failed or a driver was misused
     |    +-- LimitError          a command violated a joint limit and the policy is "fault"
     +-- KinematicsError          no inverse-kinematics solution, singular pose, bad model
     +-- CommandError             an operator command is unknown or malformed
 +-- LibraryError             the trajectory library refused or failed (occ/kinematics/trajlib.py)

``ValueError``/``TypeError`` remain for programming mistakes (bad arguments).
"""

from __future__ import annotations

from typing import TypeVar

_E = TypeVar("_E", bound=BaseException)


def caused(exc: _E, cause: BaseException) -> _E:
    """``exc`` with ``cause`` as its ``__cause__``: write ``raise caused(X(...), err) from err``.

    mypyc (2.4) ignores ``from`` in compiled code (occ/_native.py), so a compiled module sets the
    cause on the object; the ``from`` keeps the pure build (and ruff's B904) as before."""
    if exc is not cause:
        exc.__cause__ = cause
    return exc


class OCCError(Exception):
    """Base class of every error raised on purpose by :mod:`occ`."""


class ConfigError(OCCError):
    """A configuration file is invalid.

    ``errors`` holds one human-readable line per problem, each of the form
    ``FILE:LINE field.path: message``.
    """

    def __init__(self, message: str, errors: list[str] | None = None) -> None:
        super().__init__(message)
        self.errors: list[str] = list(errors) if errors else [message]


class StateError(OCCError):
    """The robot (or a component) is not in a state that allows the request."""


class DriverError(OCCError):
    """A driver could not talk to its hardware, or was used out of its lifecycle."""


class LimitError(DriverError):
    """A joint command exceeded a limit and the configured policy is to fault."""


class KinematicsError(OCCError):
    """Kinematics failed: unreachable target, singularity, or an unusable model."""


class CommandError(OCCError):
    """An operator command was unknown, malformed or refused."""


class LibraryError(OCCError):
    """The trajectory library (occ/kinematics/trajlib.py) refused a request (a bad or unknown name,
    a set
    of another robot) or its file is unusable (not a library, a newer schema, locked)."""
