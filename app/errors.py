"""Domain errors of the debugger, each with the HTTP status it stands for.

Library code (sessions, presets, the rating store) raises these; the server maps them to
responses in one place (:func:`app.api.errors.install`), so no route converts errors itself.
"""

from __future__ import annotations


class DomainError(Exception):
    """A request the debugger cannot honour, with a message for the user."""

    status = 400


class NotFound(DomainError, LookupError):
    """An unknown frame, session, stage, preset, evaluation or export."""

    status = 404


class Forbidden(DomainError):
    """A refused operation (e.g. overwriting a built-in preset)."""

    status = 403


class Conflict(DomainError):
    """The request clashes with the current state (no reconstruction yet, a running job)."""

    status = 409


class Invalid(DomainError, ValueError):
    """A bad value in the request; the message names it."""

    status = 422


class Unavailable(DomainError):
    """A resource the request needs is broken (the database, a full disk)."""

    status = 503


class TimedOut(DomainError, TimeoutError):
    """A run did not finish in time."""

    status = 504


class AlreadyExists(Conflict, FileExistsError):
    """A name that is taken (a preset saved without ``overwrite``)."""


class UserError(Exception):
    """A problem with a command-line user's input: reported in one line, no traceback."""
