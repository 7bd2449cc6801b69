"""The one exception type for bad user input.

Every loader and validator raises :class:`InputError` with one sentence that names the file, field
or value at fault. The ``simgen`` command prints that sentence (no traceback) and exits with code 2.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad user input: a missing or corrupt file, a missing field, a value out of range."""
