"""Input checks shared by every stage: one wording, one place.

Each check names the function (``fn``, when given) and the argument, says what was expected
(shape, dtype, range) and what arrived, and returns its input so that calls chain::

    r = _checks.last_dim(r, d, "r", fn="fit_limit_cycle", floating=True)

A non-tensor or a tensor of the wrong dtype is a :class:`TypeError`; a wrong shape or value is
a :class:`ValueError`.

:func:`check_value` checks an option against its type annotation (``bool``, ``int``, ``float``,
``Literal[...]``, ``X | None``) and bounds, the estimator stages' validation
(:mod:`torchconn._options`); :func:`unknown_keys_message` words a rejected key with its closest
valid one (:func:`did_you_mean`).
"""

from __future__ import annotations

import difflib
import math
import types
import typing
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "describe", "tensor", "last_dim", "finite", "integer", "broadcast_shapes", "check_shapes",
    "phase_samples",
    "first_index", "check_value", "unknown_keys_message", "did_you_mean",
]


def _at(fn: str | None) -> str:
    return f"{fn}: " if fn else ""


def describe(x) -> str:
    """What was passed: dtype and shape of a tensor, else the type's name."""
    if isinstance(x, Tensor):
        return f"{x.dtype} tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def tensor(
    x,
    name: str,
    shape: str,
    *,
    fn: str | None = None,
    valid: Callable[[Tensor], bool] | None = None,
    floating: bool = False,
) -> Tensor:
    """``x`` must be a (floating-point) tensor whose shape passes ``valid``.

    Args:
        x: the argument.
        name: its name in the caller's signature.
        shape: the expected shape in words, e.g. ``"(..., T, C) with T >= 2"``.
        fn: the public function the user called.
        valid: predicate on the tensor's shape (``None``: any shape).
        floating: require a floating-point dtype.
    """
    if not isinstance(x, Tensor) or (floating and not x.is_floating_point()):
        kind = "a floating-point torch.Tensor" if floating else "a torch.Tensor"
        raise TypeError(f"{_at(fn)}{name} must be {kind} of shape {shape}, got {describe(x)}")
    if valid is not None and not valid(x):
        raise ValueError(f"{_at(fn)}{name} must have shape {shape}, got {tuple(x.shape)}")
    return x


def last_dim(
    x, n: int, name: str, *, fn: str | None = None, why: str = "", floating: bool = False
) -> Tensor:
    """``x: (..., n)``; ``why`` completes the expected shape (e.g. ``" for a 3-joint system"``)."""
    return tensor(x, name, f"(..., {n}){why}", fn=fn, floating=floating,
                  valid=lambda t: t.ndim >= 1 and t.shape[-1] == n)


def finite(x: Tensor, name: str, *, fn: str | None = None, hint: str = "",
           nan_ok: bool = False) -> Tensor:
    """No NaN or inf in ``x`` (only no inf with ``nan_ok``, where NaN marks a missing sample).

    ``hint`` says what to do about it and is appended after a semicolon.
    """
    bad = torch.isinf(x) if nan_ok else ~torch.isfinite(x)
    if bool(bad.any()):
        what = "±inf" if nan_ok else "NaN or inf"
        raise ValueError(f"{_at(fn)}{name} contains {what}" + (f"; {hint}" if hint else ""))
    return x


def integer(value, name: str, *, minimum: int = 0, fn: str | None = None) -> int:
    """An integer (Python or NumPy, not ``bool``) ``>= minimum``, returned as an ``int``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{_at(fn)}{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def broadcast_shapes(*shapes) -> torch.Size:
    """The shape ``shapes`` (tuples of ints) broadcast to, as :func:`torch.broadcast_shapes`
    gives it, without the symbolic-shape machinery (sympy, about 0.3 s of CPU) torch's loads on
    first use.

    Raises:
        ValueError: the shapes do not broadcast.
    """
    return torch.Size(np.broadcast_shapes(*shapes))


def check_shapes(r: Tensor, d: int, name: str = "r") -> Tensor:
    """Shapes ``r: (..., d)`` handed to a system with ``d`` joints: floating, finite."""
    last_dim(r, d, name, why=f" for a system with {d} joints", floating=True)
    return finite(r, name, hint="fill or drop missing samples before asking for A(r)")


def phase_samples(phase: Tensor, r: Tensor, r_dot: Tensor, *, fn: str | None = None,
                  d: int | None = None, same_batch: bool = False, why: str = "") -> None:
    """Samples along a trajectory: ``phase: (..., T)``, ``r, r_dot: (..., T, d)``.

    Args:
        d: the number of joints the caller expects (``None``: any).
        same_batch: ``r`` must have exactly ``phase.shape + (d,)`` (else only ``T`` must
            match and the batch dims are left to broadcasting).
        why: completes the expected shape of ``r`` (e.g. ``" for a 3-joint model"``).
    """
    tensor(phase, "phase", "(..., T)", fn=fn, valid=lambda t: t.ndim >= 1)
    T = phase.shape[-1]
    dd = "d" if d is None else d
    if same_batch:
        shape = f"phase.shape + ({dd},) = {tuple(phase.shape) + (dd,)}{why}"

        def ok(t: Tensor) -> bool:
            return t.shape[:-1] == phase.shape and t.ndim > 0 and (d is None or t.shape[-1] == d)
    else:
        shape = f"(..., T={T}, {dd}) matching phase {tuple(phase.shape)}{why}"

        def ok(t: Tensor) -> bool:
            return t.ndim >= 2 and t.shape[-2] == T and (d is None or t.shape[-1] == d)
    tensor(r, "r", shape, fn=fn, valid=ok)
    tensor(r_dot, "r_dot", shape, fn=fn)
    if r_dot.shape != r.shape:
        raise ValueError(f"{_at(fn)}r_dot must have the same shape as r {tuple(r.shape)}, "
                         f"got {tuple(r_dot.shape)}")


def first_index(mask: Tensor) -> tuple[int, ...]:
    """Index of the first ``True`` in ``mask`` (C order), to name an offending element."""
    return tuple(torch.nonzero(mask)[0].tolist())


# ---------------------------------------------------------------------- option values
def _annotation_text(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_annotation_text(a) for a in typing.get_args(tp))
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
        raise ValueError(f"{where} must be {_annotation_text(tp)}, got {value!r}")
    if bounds and isinstance(value, (int, float)) and not isinstance(value, bool):
        for key, limit in bounds.items():
            ok = {"ge": value >= limit, "gt": value > limit, "le": value <= limit,
                  "lt": value < limit}[key]
            if not ok:
                rel = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}[key]
                raise ValueError(f"{where} must be {rel} {limit}, got {value!r}")


def did_you_mean(word: str, choices) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``choices``, or ``""``."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def unknown_keys_message(where: str, unknown, valid) -> str:
    """``where: unknown key 'x' (did you mean 'y'?); valid keys are …`` (closest via difflib)."""
    parts = [f"{key!r}{did_you_mean(key, valid)}" for key in sorted(map(str, unknown))]
    return f"{where}: unknown key {', '.join(parts)}; valid keys are {', '.join(sorted(valid))}"
