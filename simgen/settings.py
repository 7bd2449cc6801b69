"""Settings declared once: each field of a settings dataclass carries its type (the annotation),
default, bounds and a one-line doc with its unit, and everything else reads them from there.

    @documented
    @dataclass(frozen=True)
    class SolverConfig:
        newton_iterations: int = setting(1, low=1, doc="Newton iterations per (sub)step")

        def __post_init__(self) -> None:
            validate(self, "solver")

:func:`validate` checks every field against its declaration (raising :class:`InputError` with one
sentence naming the field and the value: "solver newton_iterations must be an integer >= 1, got 0"),
:func:`settings_of` lists the declarations (the dataset spec's ``[solver]`` table and the CLI's flags
are derived from it), :func:`documented` appends them to the class docstring. The doc starts with
the unit in brackets ("[m] ..."); unitless counts and switches have none.

Types understood (from the annotation, ``X | None`` allowing None): bool, int, float, str,
tuple[float, ...] of fixed length, dict, and nested dataclasses (checked by type only; they
validate themselves). Warp-free and torch-free.
"""

from __future__ import annotations

import functools
import math
import numbers
import types
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace

from simgen.errors import InputError

__all__ = ["setting", "Setting", "settings_of", "validate", "check_value", "documented"]

_KEY = "simgen.setting"


@dataclass(frozen=True)
class _Rule:
    low: float | None
    high: float | None
    inclusive: bool
    choices: tuple | None
    finite: bool
    doc: str


def setting(default=MISSING, *, default_factory=MISSING, low: float | None = None, high: float | None = None,
            inclusive: bool = True, choices=None, finite: bool = True, doc: str = ""):
    """A dataclass field with its bounds and doc as metadata.

    low, high: bounds of a number (``inclusive``: >= / <=, else > / <); choices: the allowed values
    of a string; finite: a float must be finite (False admits +-inf, never NaN); doc: one line,
    starting with the unit in brackets where there is one.
    """
    rule = _Rule(low, high, inclusive, tuple(choices) if choices is not None else None, finite, doc)
    return field(default=default, default_factory=default_factory, metadata={_KEY: rule})


@dataclass(frozen=True)
class Setting:
    """One declared field: name, kind (bool, int, float, str, tuple, dict, a dataclass or object),
    optional (None allowed), length (of a tuple), default (the factory's value for a factory),
    bounds, choices, finite, doc; ``nested`` is the dataclass of a nested settings class."""

    name: str
    kind: type
    optional: bool
    default: object
    low: float | None = None
    high: float | None = None
    inclusive: bool = True
    choices: tuple | None = None
    finite: bool = True
    doc: str = ""
    length: int | None = None
    types: tuple = ()

    @property
    def nested(self) -> type | None:
        return self.kind if is_dataclass(self.kind) else None

    def requirement(self) -> str:
        """What a valid value is, as a phrase: "an integer >= 1", "a finite number > 0 or None"."""
        k = self.kind
        if k is bool:
            text = "True or False"
        elif k is int:
            text = "an integer" + self.bounds()
        elif k is float:
            text = ("a finite number" if self.finite else "a number") + self.bounds()
        elif k is str:
            text = ("one of " + ", ".join(map(repr, self.choices))) if self.choices else "a string"
        elif k is tuple:
            text = f"{self.length} finite numbers"
        elif k is dict:
            text = "a dict"
        else:
            text = "a " + " or ".join(t.__name__ for t in self.types)
        return text + (" or None" if self.optional else "")

    def bounds(self) -> str:
        parts = []
        if self.low is not None:
            parts.append(f"{'>=' if self.inclusive else '>'} {self.low:g}")
        if self.high is not None:
            parts.append(f"{'<=' if self.inclusive else '<'} {self.high:g}")
        return (" " + " and ".join(parts)) if parts else ""

    def check(self, value, label: str):
        """``value`` normalised (ints of a float field become floats, a vector a tuple of floats),
        or InputError "{label} must be {requirement}, got {value!r}"."""
        if value is None and self.optional:
            return None
        k = self.kind
        ok = True
        if k is bool:
            ok = isinstance(value, bool)
        elif k is int:
            ok = isinstance(value, int) and not isinstance(value, bool) and self._in_bounds(value)
        elif k is float:
            ok = (isinstance(value, numbers.Real) and not isinstance(value, bool) and not math.isnan(value)
                  and (math.isfinite(value) or not self.finite) and self._in_bounds(value))
            if ok:
                value = float(value)
        elif k is str:
            ok = isinstance(value, str) and (self.choices is None or value in self.choices)
        elif k is tuple:
            try:
                vec = tuple(value)
            except TypeError:
                vec = None
            ok = (not isinstance(value, str) and vec is not None and len(vec) == self.length
                  and all(isinstance(c, numbers.Real) and not isinstance(c, bool) and math.isfinite(c) for c in vec))
            if ok:
                value = tuple(float(c) for c in vec)
        elif self.types:
            ok = isinstance(value, self.types)
        if not ok:
            raise InputError(f"{label} must be {self.requirement()}, got {value!r}")
        return value

    def _in_bounds(self, v) -> bool:
        if self.low is not None and (v < self.low if self.inclusive else v <= self.low):
            return False
        if self.high is not None and (v > self.high if self.inclusive else v >= self.high):
            return False
        return True

    def describe(self) -> str:
        """One line: "name (requirement; default d): doc"."""
        if self.nested:
            default = "; default None" if self.default is None else f"; default {self.kind.__name__}()"
        else:
            default = f"; default {self.default!r}"
        return f"{self.name} ({self.requirement()}{default}): {self.doc}"


def _kind(hint) -> tuple[type, bool, int | None, tuple]:
    """(kind, optional, tuple length, accepted types) of a resolved annotation."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        members = tuple(a for a in args if a is not type(None))
        optional = len(members) < len(args)
        if len(members) == 1:
            kind, _, length, accepted = _kind(members[0])
            return kind, optional, length, accepted
        accepted = tuple(typing.get_origin(m) or m for m in members)
        return object, optional, None, accepted
    origin = typing.get_origin(hint) or hint
    if origin is tuple:
        return tuple, False, len(args), (tuple,)
    return origin, False, None, (origin,)


@functools.cache
def settings_of(cls) -> dict[str, Setting]:
    """The declared settings of a dataclass (type, optional, default, bounds, doc), in field order."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in fields(cls):
        rule = f.metadata.get(_KEY)
        if rule is None:
            continue
        kind, optional, length, accepted = _kind(hints[f.name])
        default = f.default_factory() if f.default_factory is not MISSING else f.default
        out[f.name] = Setting(f.name, kind, optional, default, rule.low, rule.high, rule.inclusive, rule.choices,
                              rule.finite, rule.doc, length, accepted)
    return out


def validate(instance, where: str) -> None:
    """Check every declared field of a (frozen) dataclass instance, normalising it in place; the
    first bad one raises InputError "{where} {name} must be ..., got {value!r}"."""
    for name, s in settings_of(type(instance)).items():
        value = getattr(instance, name)
        checked = s.check(value, name if name == where else f"{where} {name}")
        if checked is not value:
            object.__setattr__(instance, name, checked)


def check_value(cls, name: str, value, label: str):
    """Check one given value against the declaration of ``cls.name`` (e.g. a command-line flag, with
    the flag as ``label``); returns it normalised. A given value is never None, so the message does
    not offer None."""
    return replace(settings_of(cls)[name], optional=False).check(value, label)


def documented(cls):
    """Class decorator: append the declared settings (requirement, default, doc) to the docstring."""
    lines = [s.describe() for s in settings_of(cls).values()]
    cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n\n    Settings (from the field declarations):\n\n" + \
        "\n".join(f"    - {line}" for line in lines) + "\n"
    return cls
