"""The shapes' observation-noise level from the tied metric model's power residuals."""

from __future__ import annotations

import torch
from torch import Tensor

#: blocks of consecutive samples over which the residual noise level's standard error is taken
_NOISE_BLOCKS = 24


def power_noise_variance(residual: Tensor, m_v: Tensor, dt: float, *, with_se: bool = False
                         ) -> Tensor | tuple[Tensor, Tensor]:
    """Observation-noise variance of the shape channels, from the power residuals' lag structure.

    The power channel is noise-free, while the model's velocity ``v̂ = v + e`` carries the
    differenced noise ``e_k = (ε_{k+1} − ε_k)/Δt``. To first order the residual of a fit
    without noise correction is ``−2 (M̂v)ᵀ e_k``, and adjacent intervals share ``ε_{k+1}``, so
    ``E[res_k res_{k+1}] = −(4/Δt²) Σ_i (M̂v)_{k,i} (M̂v)_{k+1,i} ω_i²``, while a smooth model
    error contributes the same to lags 1 and 2. Regressing ``res_k (res_{k+1} − res_{k+2})`` on
    that feature gives ``ω²``. One level is fitted for all joints (the motion-capture noise of
    every joint angle, as in docs/conventions.md): per-joint levels are too noisy to
    separate (on the 5-link at ω = 0.002 they range from 0 to 1.5× the truth).

    Args:
        residual: ``(..., N)`` ``P − P̂`` of an uncorrected fit, in time order (NaN: skipped;
            pooled trials may be concatenated when a NaN separates them).
        m_v: ``(..., N, d)`` ``M̂v`` of the same samples.
        dt: sampling interval.
        with_se: also return the standard error of ``ω²``, from the spread of the regression's
            sums over :data:`_NOISE_BLOCKS` blocks of consecutive samples (the products of
            residuals are serially correlated, so samples are not independent).

    Returns:
        ``(..., d)`` ``ω²`` (≥ 0, the same for every joint), the noise on the recorded shapes;
        with ``with_se`` also its ``(..., d)`` standard error (before clamping).
    """
    z = residual[..., :-2] * (residual[..., 1:-1] - residual[..., 2:])  # (..., N-2)
    f = -(4 / dt**2) * (m_v[..., :-2, :] * m_v[..., 1:-1, :]).sum(-1)
    ok = torch.isfinite(z) & torch.isfinite(f)
    z, f = torch.where(ok, z, 0.0), torch.where(ok, f, 0.0)
    tiny = torch.finfo(f.dtype).tiny
    omega2 = (f * z).sum(-1) / (f * f).sum(-1).clamp(min=tiny)
    shape = m_v.shape[:-2] + m_v.shape[-1:]
    out = omega2.clamp(min=0).unsqueeze(-1).expand(shape)
    if not with_se:
        return out
    # the ratio estimator's linearised spread over blocks of consecutive samples
    n_b = _NOISE_BLOCKS
    pad = (-z.shape[-1]) % n_b
    fz = _pad_last(f * z, pad).unflatten(-1, (n_b, -1)).sum(-1)
    ff = _pad_last(f * f, pad).unflatten(-1, (n_b, -1)).sum(-1)
    u = fz - omega2.unsqueeze(-1) * ff
    se = (u.square().sum(-1) * n_b / (n_b - 1)).sqrt() / ff.sum(-1).clamp(min=tiny)
    return out, se.unsqueeze(-1).expand(shape)


def _pad_last(x: Tensor, n: int) -> Tensor:
    """``x (..., N)`` with ``n`` zeros appended along the last dim."""
    return torch.cat([x, x.new_zeros(x.shape[:-1] + (n,))], -1)
