"""Recordings and fits shared by the regression tests: the 3-link swimmer on a circle
of joint angles."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression, TiedMetric, observe, simulate
from torchconn.cycles import cycle_blocks
from torchconn.physics.gaits import FourierGait
from torchconn.regression.selection import skill

from ..recordings import wave_gait

F64 = torch.float64


DT_SAMPLES = 126  # samples per cycle: Δt ≈ 0.05


def circle_gait(radius=0.9):
    coeffs = torch.zeros(3, 2, dtype=F64)
    coeffs[1, 0] = coeffs[2, 1] = radius
    return FourierGait(coeffs)


def clean_circle_trials(n_cycles=30, n_trials=4, seed=0):
    seeds = np.arange(n_trials) + 100 * seed
    return simulate(NLinkSwimmer(3), circle_gait(), eta=0.025, n_cycles=n_cycles,
                    samples_per_cycle=DT_SAMPLES, seeds=seeds)


def noisy_circle_trials(omega, n_cycles=30, n_trials=4, seed=0, clean=None):
    clean = clean_circle_trials(n_cycles, n_trials, seed) if clean is None else clean
    return observe(clean, omega, seeds=np.arange(clean.batch_shape[0]) + 100 * seed)


def fit_pooled(traj, method=NoiseAwareRegression, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ConnectionEstimator(pool=True, regression=method(**kw),
                                   metric=TiedMetric(enabled=False)).fit(traj)


def deliver_corrected_alone(monkeypatch):
    """Make NoiseAwareRegression deliver its corrected estimate alone, not shrunk towards the
    smoothed one (:func:`blend_fits` returns it with weight 1), to look at the correction."""
    import torchconn.regression.noise_aware.regression as na

    def alone(smoothed, corrected, **kwargs):
        return corrected, torch.ones(corrected.n_samples.shape[:-1] + (4,), dtype=F64)

    monkeypatch.setattr(na, "blend_fits", alone)


def a_error_and_scale(est):
    """Relative RMS error of Â along the fitted cycle and the scale s of Â ≈ s A."""
    phi = torch.linspace(0, 2 * math.pi, 201, dtype=F64)[:-1]
    a_true = NLinkSwimmer(3).connection(est.model_.gamma_at(phi))
    a_hat = est.model_.connection(phi)
    err = float((a_hat - a_true).norm() / a_true.norm())
    return err, float((a_hat * a_true).sum() / a_true.square().sum())


def index_cycle(cycle, idx):
    """Batch elements ``idx`` of a fitted LimitCycle (its series and per-element tensors)."""

    def take(x):
        return dataclasses.replace(x, coeffs=x.coeffs[idx]) if hasattr(x, "coeffs") else x[idx]

    return dataclasses.replace(cycle, **{f.name: take(getattr(cycle, f.name))
                                         for f in dataclasses.fields(cycle)})


def bin_cycle(reg, cycle):
    """The cycle at the regression's bin centres ``(..., M, d)``, as its fit passes it to
    ``noise_setup``."""
    m = reg.n_bins
    centres = torch.arange(m, dtype=F64) * (2 * math.pi / m)
    return cycle.gamma_at(centres.expand(tuple(cycle.phase_rate.shape) + (m,)))


def unpooled_trials(omega):
    """3-link circle trials of 12 cycles at 64 samples per cycle (seeds 500, 501, ...) observed
    with noise ``omega`` (one per trial), prepared, and their fitted cycle."""
    seeds = np.arange(len(omega)) + 500
    clean = simulate(NLinkSwimmer(3), circle_gait(), eta=0.025, n_cycles=12, samples_per_cycle=64,
                     seeds=seeds)
    est = ConnectionEstimator()
    prep = est.prepare(observe(clean, torch.tensor(omega, dtype=F64), seeds=seeds))
    return prep, est.cycle.fit(prep)


def gappy_circle_trials():
    """Two 3-link circle trials of 12 cycles at 64 samples per cycle, ω = 0.01, with a quarter
    of the samples (poses and shapes) lost at random."""
    seeds = np.array([61, 62])
    traj = observe(simulate(NLinkSwimmer(3), circle_gait(), eta=0.025, n_cycles=12,
                            samples_per_cycle=64, seeds=seeds), 0.01, seeds=seeds)
    lost = torch.rand(traj.r.shape[:-1], generator=torch.Generator().manual_seed(0)) < 0.25
    return traj.with_fields(pose=traj.pose.masked_fill(lost[..., None], float("nan")),
                            r=traj.r.masked_fill(lost[..., None], float("nan")))


F64 = torch.float64


WAVE_SPC = 126  # samples per cycle (Δt ≈ 0.05)


def wave_recording(n_cycles: int, n_trials: int = 1, omega: float = 0.005, seed: int = 0,
               n_links: int = 5):
    seeds = np.arange(n_trials) + 100 * seed
    clean = simulate(NLinkSwimmer(n_links), wave_gait(n_links - 1), eta=0.025, n_cycles=n_cycles,
                     samples_per_cycle=WAVE_SPC, seeds=seeds)
    return observe(clean, omega, seeds=seeds)


def fit_and_view(traj, cycle, reg, pool):
    model = reg.fit(traj, cycle, pool=pool)
    view = skill.regression_view(traj, reg, model, pool=pool, flatten=False)
    return model, view, cycle_blocks(view.phase, 3)


def assert_close_to_its_scale(a, b):
    scale = float(b[torch.isfinite(b)].abs().max())
    torch.testing.assert_close(a, b, rtol=0, atol=1e-9 * scale, equal_nan=True)


def assert_same_series_and_bins(a, b):
    """Every Fourier series and per-bin tensor of two models equal bit for bit."""
    for name in ("gamma", "c", "b", "A", "dA", "dA_fit", "M"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        assert x is None or torch.equal(x.coeffs, y.coeffs), name
    for f in dataclasses.fields(a.bins):
        x, y = getattr(a.bins, f.name), getattr(b.bins, f.name)
        assert (x is None) == (y is None), f.name
        assert x is None or torch.equal(x, y), f.name


def assert_same_model(a, b):
    """Every tensor of two models' bins and series equal bit for bit, and their meta."""
    for name in ("c", "b", "A", "dA", "c_se", "b_se", "A_se", "dA_se", "M", "M_se",
                 "M_gamma_dot", "M_gamma_dot_se", "power_on_cycle", "power_on_cycle_se"):
        x, y = getattr(a.bins, name), getattr(b.bins, name)
        assert x is not None and torch.equal(x, y), name
    for name in ("c", "b", "A", "dA", "M"):
        assert torch.equal(getattr(a, name).coeffs, getattr(b, name).coeffs), name
    assert a.meta == b.meta


def fourier_columns(phase, order):
    h = torch.arange(1, order + 1, dtype=F64)
    return torch.cat([torch.ones(phase.shape[0], 1, dtype=F64), torch.stack(
        [torch.cos(h * phase[:, None]), torch.sin(h * phase[:, None])], -1).flatten(-2)], -1)


def nine_link_three_cycles():
    """9-link reference gait, 3 cycles fitted (the next 4 kept), ω = 0.005, seed 11: no
    (bins, order) of the grid can be fitted without a third of the cycles with its full
    model's 1 + 2d + d² regressors per bin."""
    from torchconn.physics.gaits import reference_gait

    seeds = np.array([11])
    clean = simulate(NLinkSwimmer(9), reference_gait("9link"), eta=0.025, n_cycles=7,
                     samples_per_cycle=WAVE_SPC, seeds=seeds)
    traj = observe(clean, 0.005, seeds=seeds).with_fields(power=None)
    cut = 3 * WAVE_SPC + 1
    return traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)


F64 = torch.float64


# ----------------------------------------------------------------------------- helpers
def circle(phi: torch.Tensor, d: int, radius: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """A circle of ``radius`` in the first two joints (others 0) and its φ-derivative."""
    g = torch.zeros(phi.shape + (d,), dtype=F64)
    gd = torch.zeros(phi.shape + (d,), dtype=F64)
    g[..., 0], g[..., 1] = radius * torch.cos(phi), radius * torch.sin(phi)
    gd[..., 0], gd[..., 1] = -radius * torch.sin(phi), radius * torch.cos(phi)
    return g, gd


def tube_samples(batch, n, d, *, sigma=0.1, sigma_dot=0.1, seed=0, cycles=20):
    """Phases uniform over many cycles, ``r = γ(φ) + δ``, ``ṙ = γ'(φ) + δ̇``."""
    gen = torch.Generator().manual_seed(seed)
    phi = torch.rand(batch + (n,), generator=gen, dtype=F64) * (2 * math.pi * cycles)
    g, gd = circle(phi, d)
    r = g + sigma * torch.randn(batch + (n, d), generator=gen, dtype=F64)
    r_dot = gd + sigma_dot * torch.randn(batch + (n, d), generator=gen, dtype=F64)
    return phi, r, r_dot, gen


def cycle_at_centres(n_bins: int, d: int):
    phi_m = torch.arange(n_bins, dtype=F64) * (2 * math.pi / n_bins)
    return circle(phi_m, d)


def reference_rows(bins, b, m, *arrays):
    """The weighted rows of bin ``m`` of batch element ``b`` as numpy arrays."""
    k = int(bins.count[b, m])
    idx = bins.index[b, m, :k].numpy()
    w = bins.weight[b, m, :k].numpy()
    keep = w > 0
    return (w[keep],) + tuple(a[b].numpy()[idx[keep]] for a in arrays)


def reference_fit(x, y, w):
    """lstsq on √w-weighted rows, and the sandwich standard errors with the effective dof."""
    sw = np.sqrt(w)[:, None]
    beta = np.linalg.lstsq(sw * x, sw * y, rcond=None)[0]
    a = x.T @ (w[:, None] * x)
    g2 = x.T @ ((w**2)[:, None] * x)
    a_inv = np.linalg.inv(a)
    dof = w.sum() - np.trace(a_inv @ g2)
    sigma2 = (w[:, None] * (y - x @ beta) ** 2).sum(0) / dof
    cov = a_inv @ g2 @ a_inv
    return beta, np.sqrt(np.outer(np.diag(cov), sigma2))
