"""Immutable option objects for the estimator's stages (smoother, phaser, cycle, regression).

A stage is a frozen, keyword-only dataclass deriving from :class:`Options`. Its fields are
checked against their annotations when it is built -- ``bool``, ``int``, ``float``,
``typing.Literal[...]`` and ``X | None`` -- and against bounds given with :func:`option`, so
every stage reports a bad value the same way: the class, the field, what is allowed and what
it got. Cross-field rules go in the subclass's ``__post_init__`` after ``super().__post_init__()``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from typing import Any, Literal

__all__ = ["Options", "option", "check_value", "unknown_keys_message"]

_MISSING = dataclasses.MISSING


def option(default: Any = _MISSING, *, ge: float | None = None, gt: float | None = None,
           le: float | None = None) -> Any:
    """A dataclass field with bounds ``ge <= value``, ``gt < value``, ``value <= le`` (numbers)."""
    bounds = {k: v for k, v in (("ge", ge), ("gt", gt), ("le", le)) if v is not None}
    return dataclasses.field(default=default, metadata={"bounds": bounds})


def _describe(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "None"
    if tp is float:
        return "a finite number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    return getattr(tp, "__name__", str(tp))


def _matches(value: Any, tp: Any) -> bool:
    origin = typing.get_origin(tp)
    if origin is Literal:
        # 2 == 2.0 == True in Python: compare types too, so order=True is not order=1
        return any(value == a and type(value) is type(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value))
    if tp is str:
        return isinstance(value, str)
    return True  # other annotations (objects) are checked by the owner


def check_value(where: str, value: Any, tp: Any, bounds: dict | None = None) -> None:
    """Raise ``ValueError`` naming ``where`` unless ``value`` fits annotation ``tp`` and ``bounds``."""
    if not _matches(value, tp):
        raise ValueError(f"{where} must be {_describe(tp)}, got {value!r}")
    if bounds and isinstance(value, (int, float)) and not isinstance(value, bool):
        for key, limit in bounds.items():
            ok = {"ge": value >= limit, "gt": value > limit, "le": value <= limit}[key]
            if not ok:
                rel = {"ge": ">=", "gt": ">", "le": "<="}[key]
                raise ValueError(f"{where} must be {rel} {limit}, got {value!r}")


class Options:
    """Base of the stage option objects: validation from annotations, scikit-learn params.

    Subclasses are ``@dataclass(frozen=True, kw_only=True)``. They are values: equal when their
    fields are equal, changed only by :meth:`replace`, so one object can be shared by many
    estimators and :func:`sklearn.base.clone` copies them safely.
    """

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            check_value(f"{type(self).__name__}.{f.name}", getattr(self, f.name), hints[f.name],
                        f.metadata.get("bounds"))

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The fields as a dict (scikit-learn's protocol; the options hold no sub-estimators)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def replace(self, **changes: Any):
        """A copy with some fields changed (and validated again); unknown names are rejected."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(unknown_keys_message(type(self).__name__, unknown, self.get_params()))
        return dataclasses.replace(self, **changes)


def unknown_keys_message(where: str, unknown, valid) -> str:
    """``where: unknown key 'x' (did you mean 'y'?); valid keys are …`` (closest via difflib)."""
    parts = []
    for key in sorted(map(str, unknown)):
        close = difflib.get_close_matches(key, list(valid), n=1)
        parts.append(f"{key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return f"{where}: unknown key {', '.join(parts)}; valid keys are {', '.join(sorted(valid))}"
