"""The typed diagnostics of a fit (RegressionDiagnostics)."""

import dataclasses

import pytest
import torch

from torchconn import (
    NoiseAwareRegression,
    TubeRegression,
)
from torchconn.regression import (
    LocalConnectionModel,
)


def test_a_fits_diagnostics_are_the_choices_its_meta_records(eight, tmp_path):
    """The typed diagnostics selection reads carry the fit's own choices: a noise-aware
    fit's interval, noise level and blend weights per trial, a tube fit's window and no
    noise-aware fields; a model saved and loaded keeps them."""
    traj, cycle, _ = eight
    noisy = NoiseAwareRegression(n_bins=16, fourier_order=4).fit(
        traj, cycle, pool=False)
    diag = noisy.diagnostics
    assert torch.equal(torch.as_tensor(diag.velocity_interval),
                       torch.as_tensor(noisy.meta["velocity_interval"]))
    assert torch.as_tensor(diag.noise_r).shape == (2, 4)  # trials, joints
    assert torch.equal(torch.as_tensor(diag.noise_r), torch.as_tensor(noisy.meta["noise_r"]))
    weight = torch.as_tensor(diag.corrected_weight)
    assert weight.shape == (2, 4) and bool(((weight >= 0) & (weight <= 1)).all())
    assert diag.velocity_kernel == noisy.meta["velocity_kernel"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        diag.window = 1.0
    assert LocalConnectionModel.load(noisy.save(tmp_path / "model")).diagnostics == diag
    tube = TubeRegression(n_bins=16, fourier_order=4, window=2.0).fit(
        traj, cycle, pool=False)
    assert tube.diagnostics.window == 2.0
    assert tube.diagnostics.noise_r is None and tube.diagnostics.corrected_weight is None
