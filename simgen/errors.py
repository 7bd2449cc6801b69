"""simgen's exception types.

Every loader and validator raises :class:`InputError` with one sentence that names the file, field
or value at fault. The ``simgen`` command prints that sentence (no traceback) and exits with code 2.
:class:`GenerationError`: a dataset run that could not finish (the store stays consistent).
"""

from __future__ import annotations

__all__ = ["InputError", "GenerationError"]


class InputError(ValueError):
    """Bad user input: a missing or corrupt file, a missing field, a value out of range."""


class GenerationError(RuntimeError):
    """A dataset run could not finish (a Ray task failed beyond its retries); the store stays
    consistent and the next run resumes it."""
