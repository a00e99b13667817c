"""The physics prior: a fitted model's rows shrunk towards a physical reference's, held out.

Where a recording holds few cycles, the data-driven model's offset terms and even its
connection are poorly determined, and the sensible thing to pull them towards is a physical
model of the same body (:mod:`torchconn.regression.reference`), not zero. For each body-velocity
component the forecast is the blend ``(1 − w)·model + w·reference`` of the two local models'
rows (``c``, ``b``, ``A``, ``∂A/∂r``), with ``w ∈ [0, 1]`` the weight that minimises the
squared error on held-out cycles, kept only where it lowers that error clearly
(:data:`PRIOR_Z` standard errors of the sum over held-out cycles). On long recordings the
fitted model wins and ``w`` is 0; where the reference predicts better, ``w`` grows to 1.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...phase.fourier import FourierSeries
from ..model import LocalConnectionModel
from .complexity import lower_by

__all__ = ["PRIOR_Z", "PRIOR_MARGIN", "prior_weights", "forward_checked", "blend",
           "blended_r2"]

#: standard errors (of the sum over held-out cycles of the per-cycle change of squared error)
#: by which the blend must beat the fitted model for its weight to be kept
PRIOR_Z = 2.0
#: and the fraction of the fitted model's held-out squared error it must save
PRIOR_MARGIN = 0.05


def prior_weights(y: Tensor, fitted: Tensor, reference: Tensor, cycle: Tensor,
                  z: float = PRIOR_Z, margin: float = PRIOR_MARGIN) -> Tensor:
    """The prior's weight per component, ``(..., 3)`` in ``[0, 1]``.

    Args:
        y: ``(..., N, 3)`` held-out body velocity (NaN: not scored).
        fitted, reference: ``(..., N, 3)`` the fitted model's and the reference's held-out
            predictions of it (each sample predicted by the fit without its block).
        cycle: ``(..., N)`` each sample's whole cycle (``-1``: none), the unit whose scatter
            gives the standard error.
        z, margin: see :data:`PRIOR_Z`, :data:`PRIOR_MARGIN`.

    Returns:
        ``w = Σ e·δ / Σ δ²`` clipped to ``[0, 1]`` (``e = y − fitted``, ``δ = reference −
        fitted``), the minimiser of the blend's squared error; 0 where the blend does not
        lower the fitted model's error by more than ``z`` standard errors and the fraction
        ``margin`` of it.
    """
    ok = (torch.isfinite(y) & torch.isfinite(fitted) & torch.isfinite(reference)
          & (cycle >= 0).unsqueeze(-1))
    e = torch.where(ok, y - fitted, 0.0)
    d = torch.where(ok, reference - fitted, 0.0)
    dd = (d * d).sum(-2)
    w = ((e * d).sum(-2) / dd.clamp_min(torch.finfo(dd.dtype).tiny)).clamp(0.0, 1.0)
    # per cycle, the change of squared error at that weight: w²δ² − 2w·e·δ
    change = w.unsqueeze(-2) * (w.unsqueeze(-2) * d * d - 2 * e * d)
    n_cycles = int(cycle.amax()) + 1 if cycle.numel() else 0
    index = torch.where(cycle >= 0, cycle, n_cycles).unsqueeze(-1).expand(change.shape)
    per_cycle = change.new_zeros(change.shape[:-2] + (n_cycles + 1, 3)).scatter_add(
        -2, index, change)[..., :-1, :]
    clear = lower_by(per_cycle, z) & (change.sum(-2) < -margin * (e * e).sum(-2))
    return torch.where(clear, w, torch.zeros_like(w))


def forward_checked(weight: Tensor, y: Tensor, fitted: Tensor, reference: Tensor,
                    forward: Tensor) -> Tensor:
    """``weight`` (:func:`prior_weights`), raised to 1 (the reference alone) for each
    component where the reference predicts better than the blend both on every held-out
    block and on the forward-in-time block alone (``forward (..., N)``: the samples of the
    last block, predicted by the fits to the earlier ones); arguments otherwise as
    :func:`prior_weights`'s. A forecast is thus delivered only where it does not lose to the
    physics on both checks."""
    ones = torch.ones_like(weight)
    loses = torch.ones_like(weight, dtype=torch.bool)
    for mask in (None, forward):
        blended = blended_r2(y, fitted, reference, weight, mask)
        physics = blended_r2(y, fitted, reference, ones, mask)
        loses &= physics > blended
    return torch.where(loses, ones, weight)


def blend(model: LocalConnectionModel, reference: LocalConnectionModel, weight: Tensor
          ) -> LocalConnectionModel:
    """``model`` with each component's rows of ``c``, ``b``, ``A`` and ``∂A/∂r`` replaced by
    ``(1 − w)·model + w·reference`` (``weight (..., 3)``; the reference a local model at the
    same cycle, :meth:`~torchconn.regression.reference.PhysicsReference.local_model`);
    ``model`` itself where every weight is 0. ``meta["prior_weight"]`` records the weights."""
    weight = torch.as_tensor(weight, dtype=model.c.coeffs.dtype, device=model.device)
    if not bool((weight > 0).any()):
        return model

    def mixed(a: FourierSeries, b: FourierSeries | None) -> FourierSeries:
        b = b if b is not None else a
        order = max(a.order, b.order)
        x, y = a.padded(order).coeffs, b.padded(order).coeffs.to(a.coeffs)
        w = weight.reshape(weight.shape[:-1] + (1, 3) + (1,) * (a.value_ndim - 1))
        return FourierSeries(x + w * (y - x), a.value_ndim)

    dA = mixed(model.dA, reference.dA)
    return dataclasses.replace(
        model, c=mixed(model.c, reference.c), b=mixed(model.b, reference.b),
        A=mixed(model.A, reference.A), dA=dA,
        dA_fit=None if model.dA_fit is None else mixed(model.dA_fit, reference.dA),
        meta={**(model.meta or {}), "prior_weight": weight.tolist()})


def blended_r2(y: Tensor, fitted: Tensor, reference: Tensor, weight: Tensor,
               mask: Tensor | None = None) -> Tensor:
    """``(..., 3)`` the ``R²`` of the blend ``fitted + w·(reference − fitted)`` (arguments as
    :func:`prior_weights`'s, ``weight (..., 3)``) over the scored samples (and ``mask
    (..., N)``, where given): the held-out skill of the shrunk forecasts."""
    ok = torch.isfinite(y) & torch.isfinite(fitted)
    if mask is not None:
        ok &= mask.unsqueeze(-1)
    pred = fitted + torch.where(torch.isfinite(reference), weight.unsqueeze(-2)
                                * (reference - fitted), 0.0)
    w = ok.to(y.dtype)
    y0 = torch.where(ok, y, 0.0)
    n = w.sum(-2)
    sst = (y0.square() * w).sum(-2) - (y0 * w).sum(-2).square() / n
    return 1 - (torch.where(ok, y - pred, 0.0).square()).sum(-2) / sst

