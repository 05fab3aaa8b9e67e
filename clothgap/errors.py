"""The project's user-error types (no imports: every stage module may use them).

A ``UserError`` is bad input the user can fix (a setting, a name, a path): the
``clothgap`` command prints its message as ``error: ...`` and exits non-zero,
without a traceback. Anything else that escapes a command is a bug and keeps
its traceback. The specific types also derive from the built-in exception a
caller would expect (``ValueError``, ``FileNotFoundError``, ...).
"""

from __future__ import annotations


class UserError(Exception):
    """Bad input from the user; the message says what is wrong and, where it can, what is allowed."""


class ConfigError(UserError, ValueError):
    """A config, preset or override the user gave is wrong; the message says how."""


class InputError(UserError, ValueError):
    """An input file the user named is malformed (e.g. a CSV without a needed column); the message names it."""


class MissingInputError(UserError, FileNotFoundError):
    """A file or folder the user named (or a stage's input) does not exist; the message names it."""


class StorageError(UserError, OSError):
    """The disk refused a write (full, read-only, no permission); the message names the path.

    What was finished is kept and nothing half-written is left to be trusted, so the same
    command resumes once the user has made room or fixed the permissions.
    """
