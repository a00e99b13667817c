"""Immutable option objects for the estimator's stages (smoother, phaser, cycle, regression).

A stage is a frozen, keyword-only dataclass deriving from :class:`Options`. Its fields are
checked against their annotations when it is built -- ``bool``, ``int``, ``float``,
``typing.Literal[...]`` and ``X | None`` -- and against bounds given with :func:`option`, so
every stage reports a bad value the same way: the class, the field, what is allowed and what
it got (:func:`torchconn._checks.check_value`). Cross-field rules go in the subclass's
``__post_init__`` after ``super().__post_init__()``.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from ._checks import check_value, unknown_keys_message

__all__ = ["Options", "option", "check_field", "check_value", "unknown_keys_message"]

_MISSING = dataclasses.MISSING


def option(default: Any = _MISSING, *, ge: float | None = None, gt: float | None = None,
           le: float | None = None, lt: float | None = None) -> Any:
    """A dataclass field with bounds ``ge <= value``, ``gt < value``, ``value <= le``,
    ``value < lt`` (numbers)."""
    bounds = {k: v for k, v in (("ge", ge), ("gt", gt), ("le", le), ("lt", lt)) if v is not None}
    return dataclasses.field(default=default, metadata={"bounds": bounds})


def check_field(cls: type, name: str, value: Any, where: str) -> None:
    """Raise ``ValueError`` naming ``where`` unless ``value`` fits the field ``name`` of the
    option class ``cls`` (its annotation and bounds); what ``cls(name=value)`` checks, worded
    for where the value came from (a config key, a flag)."""
    field = {f.name: f for f in dataclasses.fields(cls)}[name]
    check_value(where, value, typing.get_type_hints(cls)[name], field.metadata.get("bounds"))


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
