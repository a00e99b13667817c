"""Fourier series in phase: exact fits of band-limited functions, calculus, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchconn.phase.fourier import FourierSeries, fit_fourier, fourier_design, fourier_on_grid

from .common import periodic_signal

DT = torch.float64


def _random_series(gen, batch, order, value_shape):
    c = torch.randn(*batch, 2 * order + 1, *value_shape, generator=gen, dtype=DT)
    return FourierSeries(c, len(value_shape))


def _scattered_phases(gen, batch, T):
    # arbitrary (unsorted, non-uniform, unwrapped) phases covering the circle
    return 2 * math.pi * torch.rand(*batch, T, generator=gen, dtype=DT) ** 1.5 * 3 - 4.0


@pytest.mark.parametrize("value_shape", [(), (4,), (3, 2), (3, 2, 2)])
def test_fit_recovers_band_limited_function_exactly(value_shape):
    gen = torch.Generator().manual_seed(0)
    batch, order = (2, 3), 4
    truth = _random_series(gen, batch, order, value_shape)
    phi = _scattered_phases(gen, batch, 60)
    values = truth(phi)
    assert values.shape == (*batch, 60, *value_shape)
    fit = fit_fourier(phi, values, order)
    assert fit.value_shape == value_shape and fit.batch_shape == batch and fit.order == order
    assert torch.allclose(fit.coeffs, truth.coeffs, atol=1e-10, rtol=0)
    # a higher order fit finds zero extra harmonics
    hi = fit_fourier(phi, values, order + 2)
    assert torch.allclose(hi(phi), values, atol=1e-10, rtol=0)
    assert hi.coeffs[..., 2 * order + 1 :, *([slice(None)] * len(value_shape))].abs().max() < 1e-10


def test_series_evaluates_its_definition():
    c = torch.tensor([0.5, 1.0, -2.0, 0.25, 3.0], dtype=DT)  # a0, a1, b1, a2, b2
    s = FourierSeries(c)
    phi = torch.linspace(0, 7, 11, dtype=DT)
    want = (
        0.5
        + torch.cos(phi)
        - 2 * torch.sin(phi)
        + 0.25 * torch.cos(2 * phi)
        + 3 * torch.sin(2 * phi)
    )
    assert torch.allclose(s(phi), want, atol=1e-14)
    assert torch.allclose(s(torch.tensor(1.3, dtype=DT)), s(torch.tensor([1.3], dtype=DT))[0])
    assert s.mean().item() == 0.5
    X = fourier_design(phi, 2)
    assert X.shape == (11, 5) and torch.allclose(X @ c, want, atol=1e-14)


def test_evaluation_broadcasts_phases_against_batch():
    gen = torch.Generator().manual_seed(1)
    s = _random_series(gen, (3,), 2, (2,))
    phi = torch.linspace(0, 6, 7, dtype=DT)
    out = s(phi)  # shared phases
    assert out.shape == (3, 7, 2)
    per = torch.stack([FourierSeries(s.coeffs[i], 1)(phi) for i in range(3)])
    assert torch.allclose(out, per, atol=1e-14)
    assert s(phi.expand(5, 3, 7)).shape == (5, 3, 7, 2)


def test_derivative_and_integral_round_trip():
    gen = torch.Generator().manual_seed(2)
    s = _random_series(gen, (2,), 5, (3, 2))
    phi = torch.linspace(-1, 9, 201, dtype=DT)
    # derivative against autograd on the evaluated series
    p = phi.clone().requires_grad_(True)
    y = s(p)
    g = torch.stack(
        [
            torch.autograd.grad(y[..., i, j].sum(), p, retain_graph=True)[0]
            for i in range(3)
            for j in range(2)
        ],
        -1,
    ).reshape(201, 3, 2)
    d1 = s.derivative()
    assert torch.allclose(d1(phi).sum(0), g, atol=1e-10)
    # nth derivatives compose; integral inverts derivative up to the mean
    assert torch.allclose(s.derivative(3).coeffs, d1.derivative(2).coeffs, atol=1e-12)
    back = d1.integral()
    assert torch.allclose(back.coeffs[..., 1:, :, :], s.coeffs[..., 1:, :, :], atol=1e-12)
    assert back.mean().abs().max() == 0
    assert torch.allclose(back.derivative().coeffs, d1.coeffs, atol=1e-12)
    assert s.derivative(0) is s


def test_integral_refuses_nonzero_mean_unless_dropped():
    s = FourierSeries(torch.tensor([0.3, 1.0, 0.0], dtype=DT))
    with pytest.raises(ValueError, match="nonzero mean"):
        s.integral()
    i = s.integral(drop_mean=True)  # integrates only cos(phi) -> sin(phi)
    assert torch.allclose(i.coeffs, torch.tensor([0.0, 0.0, 1.0], dtype=DT))


def test_weights_and_nan_samples_are_ignored():
    gen = torch.Generator().manual_seed(3)
    truth = _random_series(gen, (), 3, (2,))
    phi = _scattered_phases(gen, (), 80)
    values = truth(phi)
    corrupt = values.clone()
    corrupt[::5] += 10.0  # outliers, given zero weight
    corrupt[1::7, 0] = float("nan")  # drop-outs, ignored automatically
    w = torch.ones(80, dtype=DT)
    w[::5] = 0.0
    fit = fit_fourier(phi, corrupt, 3, weights=w)
    assert torch.allclose(fit.coeffs, truth.coeffs, atol=1e-10)
    phi_nan = phi.clone()
    phi_nan[2] = float("nan")
    assert torch.isfinite(fit_fourier(phi_nan, values, 3).coeffs).all()


def test_ridge_shrinks_harmonics_not_mean():
    phi = torch.arange(200, dtype=DT) * (2 * math.pi / 20)  # 10 uniform cycles
    y = 2.0 + torch.cos(phi)
    c = fit_fourier(phi, y, 1, ridge=1.0).coeffs
    # normal equations diag(1, 1/2, 1/2) + ridge on harmonics: a1 = (1/2) / (1/2 + 1)
    assert torch.allclose(c, torch.tensor([2.0, 1 / 3, 0.0], dtype=DT), atol=1e-12)


def test_follows_dtype():
    phi = torch.linspace(0, 6.2, 20, dtype=torch.float32)
    fit = fit_fourier(phi, torch.sin(phi), 2)
    assert fit.coeffs.dtype == torch.float32


def test_errors_are_clear():
    phi = torch.linspace(0, 6, 5, dtype=DT)
    with pytest.raises(ValueError, match="at least 7 samples"):
        fit_fourier(phi, torch.sin(phi), 3)
    with pytest.raises(ValueError, match="order must be an integer >= 0"):
        fit_fourier(phi, torch.sin(phi), -1)
    with pytest.raises(ValueError, match="T=5 samples"):
        fit_fourier(phi, torch.zeros(6, 2, dtype=DT), 1, value_ndim=1)
    with pytest.raises(ValueError, match="weights must have shape"):
        fit_fourier(phi, torch.sin(phi), 1, weights=torch.ones(4, dtype=DT))
    with pytest.raises(ValueError, match="do not cover the circle"):
        narrow = torch.full((50,), 0.3, dtype=DT) + 1e-9 * torch.arange(50, dtype=DT)
        fit_fourier(narrow, torch.sin(narrow), 2)
    with pytest.raises(ValueError, match="odd length"):
        FourierSeries(torch.zeros(4, dtype=DT))


@pytest.mark.parametrize("value_shape", [(), (3, 2)])
def test_fourier_on_grid_is_the_least_squares_fit(value_shape):
    """On an equispaced grid the FFT gives fit_fourier's coefficients (noisy, not band-limited
    values, orders up to the highest below Nyquist)."""
    gen = torch.Generator().manual_seed(3)
    n = 64
    grid = torch.arange(n, dtype=DT) * (2 * math.pi / n)
    values = torch.randn(2, n, *value_shape, generator=gen, dtype=DT)
    for order in (0, 5, n // 2 - 1):
        fast = fourier_on_grid(values, order, value_ndim=len(value_shape))
        slow = fit_fourier(grid, values, order, value_ndim=len(value_shape))
        assert fast.order == order and fast.value_shape == value_shape
        torch.testing.assert_close(fast.coeffs, slow.coeffs, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="order 32 needs more than 64 grid samples"):
        fourier_on_grid(values, n // 2, value_ndim=len(value_shape))


def test_truncated_zeroes_the_harmonics_above_each_elements_order():
    phi = torch.linspace(0, 2 * math.pi, 48, dtype=torch.float64)[:-1]
    values = torch.stack([periodic_signal(phi, (1, 4, 7)), periodic_signal(phi, (1, 4, 7))]).unsqueeze(-1)
    series = fit_fourier(phi, values, 10, value_ndim=1)
    cut = series.truncated(torch.tensor([4, 10]))
    low = fit_fourier(phi, values, 4, value_ndim=1)
    torch.testing.assert_close(cut(phi)[0], low(phi)[0])  # equispaced: truncation = refit
    torch.testing.assert_close(cut(phi)[1], values[1])
    assert isinstance(cut, FourierSeries) and cut.order == 10


F64 = torch.float64


PHI = torch.linspace(0, 2 * math.pi, 49, dtype=F64)[:-1]


def test_fourier_series_padded_is_the_same_function():
    g = torch.Generator().manual_seed(1)
    s = FourierSeries(torch.randn(2, 7, 3, generator=g, dtype=F64), 1)
    p = s.padded(6)
    assert p.coeffs.shape == (2, 13, 3) and s.padded(2) is s
    torch.testing.assert_close(p(PHI), s(PHI), rtol=0, atol=1e-14)
