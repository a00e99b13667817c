"""The paper's per-bin metric regression (``torchconn.testing.paper_metric``), kept as a
reference: exact for an affine metric, constant without a derivative, and the per-bin least
squares."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn.physics.systems import AffineConnectionSystem
from torchconn.regression import assign_bins
from torchconn.testing.paper_metric import metric_regression

from ..common import cycle_at_centres, reference_fit, reference_rows, tube_samples

F64 = torch.float64


# ----------------------------------------------------------------------------- metric
def affine_metric(d: int, seed: int = 0):
    """``M(r) = M0 + Σ_k M1[..., k] r_k``: symmetric, positive definite near the cycle."""
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(d, d, generator=gen, dtype=F64)
    m0 = q @ q.T + d * torch.eye(d, dtype=F64)
    m1 = 0.3 * torch.randn(d, d, d, generator=gen, dtype=F64)
    m1 = (m1 + m1.transpose(0, 1)) / 2  # [i, j, k] = ∂M_ij/∂r_k

    def metric(r):
        return m0 + torch.einsum("ijk,...k->...ij", m1, r)

    return metric, m1


@pytest.mark.parametrize("d", [2, 3])
def test_metric_exact_for_affine_metric(d):
    metric, m1 = affine_metric(d, seed=d)
    phi, r, r_dot, _ = tube_samples((2,), 4000, d, seed=20 + d)
    power = torch.einsum("...i,...ij,...j->...", r_dot, metric(r), r_dot)
    bins = assign_bins(phi, 6)
    g_m, gd_m = cycle_at_centres(6, d)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m)
    assert fit.dM is not None  # enough samples: the derivative block is fitted by default
    torch.testing.assert_close(fit.M, metric(g_m).expand_as(fit.M), atol=1e-8, rtol=0)
    torch.testing.assert_close(fit.dM, m1.expand_as(fit.dM), atol=1e-8, rtol=0)
    p_cycle = torch.einsum("mi,mij,mj->m", gd_m, metric(g_m), gd_m)
    torch.testing.assert_close(fit.power_on_cycle, p_cycle.expand_as(fit.power_on_cycle),
                               atol=1e-8, rtol=0)
    assert torch.equal(fit.M, fit.M.mT) and fit.se_M.shape == fit.M.shape


def test_metric_constant_without_derivative():
    d = 3
    system = AffineConnectionSystem.random(d, seed=9)
    phi, r, r_dot, _ = tube_samples((), 1200, d, seed=9)
    power = system.power(r, r_dot)
    g_m, gd_m = cycle_at_centres(8, d)
    bins = assign_bins(phi, 8)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m, with_metric_derivative=False)
    assert fit.dM is None and fit.se_dM is None
    torch.testing.assert_close(fit.M, system.metric(g_m), atol=1e-8, rtol=0)
    # automatic choice: too few samples per bin for the 3rd-order block in d = 8 → left out
    phi8, r8, rd8, _ = tube_samples((), 1200, 8, seed=9)
    fit8 = metric_regression(r8, rd8, (rd8**2).sum(-1), assign_bins(phi8, 8),
                             *cycle_at_centres(8, 8))
    assert fit8.dM is None
    torch.testing.assert_close(fit8.M, torch.eye(8, dtype=F64).expand_as(fit8.M), atol=1e-8,
                               rtol=0)


def test_metric_matches_per_bin_lstsq():
    d = 2
    metric, _ = affine_metric(d, seed=1)
    phi, r, r_dot, gen = tube_samples((2,), 1500, d, seed=12)
    power = torch.einsum("...i,...ij,...j->...", r_dot, metric(r), r_dot) \
        + 0.05 * torch.randn(2, 1500, generator=gen, dtype=F64) + 0.2 * r[..., 0] ** 2
    bins = assign_bins(phi, 5, window=0.7, kernel="epanechnikov")
    g_m, gd_m = cycle_at_centres(5, d)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m, with_metric_derivative=True)
    iu = np.triu_indices(d)
    for b in range(2):
        for m in range(5):
            w, rr, rd, y = reference_rows(bins, b, m, r, r_dot, power.unsqueeze(-1))
            de, dd = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            quad = dd[:, iu[0]] * dd[:, iu[1]]
            x = np.concatenate([np.ones((len(w), 1)), dd, quad, de,
                                np.einsum("nk,nj->nkj", de, dd).reshape(len(w), -1),
                                np.einsum("nk,nq->nkq", de, quad).reshape(len(w), -1)], 1)
            beta, se = reference_fit(x, y, w)
            assert np.abs(fit.coef[b, m].numpy() - beta[:, 0]).max() <= 1e-10 * np.abs(beta).max()
            np.testing.assert_allclose(fit.se_coef[b, m].numpy(), se[:, 0], rtol=1e-8)
