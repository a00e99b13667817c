"""Leave-blocks-out fits by downdated normal equations (``skill.held_out_coefficients``) against
true refits without each block, with and without the noise correction."""

import pytest
import torch

from torchconn import NoiseAwareRegression, TubeRegression
from torchconn.noise import IntervalSamples
from torchconn.regression import assign_bins, connection_regression
from torchconn.regression.noise_aware import noise_aware_regression
from torchconn.regression.selection import skill

from ..common import assert_close_to_its_scale, fit_and_view

F64 = torch.float64


@pytest.mark.parametrize("ridge", [0.0, 0.3])
def test_downdated_fits_equal_refits_without_each_block(eight, ridge):
    traj, cycle, _ = eight
    reg = TubeRegression(n_bins=24, fourier_order=6, window=2.0)
    model, view, fold = fit_and_view(traj, cycle, reg, pool=False)
    coef = skill.held_out_coefficients(traj, reg, model, view, fold, 3, pool=False,
                                       ridges=(ridge,))[0]
    for f in range(3):
        bins = assign_bins(torch.where(fold == f, torch.nan, view.phase), 24, window=2.0,
                           kernel="tricube")
        refit = connection_regression(view.r, view.r_dot, view.xi, bins, model.bins.gamma,
                                      model.bins.gamma_dot, ridge=ridge)
        assert_close_to_its_scale(coef[f], refit.coef)


def test_downdated_noise_aware_fits_equal_refits_with_the_noise_correction(eight):
    traj, _, cycle = eight
    reg = NoiseAwareRegression(n_bins=16, fourier_order=4)
    model, view, fold = fit_and_view(traj, cycle, reg, pool=True)
    assert float(torch.as_tensor(model.meta["noise_r"]).min()) > 0  # the correction is on
    coef = skill.held_out_coefficients(traj, reg, model, view, fold, 3, pool=True)[0]
    h = model.meta["velocity_interval"]
    var = torch.as_tensor(model.meta["noise_r"], dtype=F64).square()
    flat = [x.reshape((-1,) + x.shape[2:]) for x in (view.phase, view.r, view.r_dot, view.xi)]
    for f in range(3):
        phase = torch.where(fold.reshape(-1) == f, torch.nan, flat[0])
        samples = IntervalSamples(phase, *flat[1:], h=h, dt=traj.dt)
        bins = assign_bins(phase, 16, window=model.meta["window"], kernel="tricube")
        refit = noise_aware_regression(samples, bins, model.bins.gamma, model.bins.gamma_dot,
                                       var)
        assert_close_to_its_scale(coef[f], refit.coef)
