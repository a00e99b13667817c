"""The pipeline follows its inputs' device.

simulate -> observe -> ConnectionEstimator().fit -> evaluation models on every available
device (CUDA when present, skipped otherwise), and, on any machine, a guard that no tensor
on the path is created on torch's default device instead of the inputs' one: the pipeline
runs on CPU inputs with the default device set to ``meta``, so a factory call without
``device=`` (``torch.zeros(n)``, ``torch.tensor(list)``, ...) yields a ``meta`` tensor and fails
the test. That is exactly the tensor that would land on the CPU beside CUDA inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression, observe, simulate
from torchconn.evaluation.models import (
    clean_trajectory,
    error_summary,
    phase_bin_errors,
    reference_models,
)
from torchconn.physics.gaits import reference_gait

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                  reason="needs CUDA")),
]
SEEDS = np.arange(4)


def _data(device: str, n_cycles: int = 12):
    eta = torch.tensor(0.025, dtype=torch.float64, device=device)
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=eta, n_cycles=n_cycles,
                    seeds=SEEDS)
    return observe(traj, 0.002, seeds=SEEDS)


def _pipeline(traj, system):
    """Fit both regressions and evaluate; every output tensor, keyed by a name."""
    est = ConnectionEstimator().fit(traj)
    phi = torch.linspace(0, 2 * np.pi, 17, dtype=traj.r.dtype, device=traj.r.device)
    prep = est.trajectory_
    models = reference_models(system, est.model_, prep, clean_trajectory(traj))
    out = {"A": est.model_.connection(phi), "predict": est.predict(traj),
           "metric": est.model_.metric(phi), "A_se": est.model_.bins.A_se,
           "rms": error_summary(models["data_driven"], models["ground_truth"]),
           "noise_aware": ConnectionEstimator(regression=NoiseAwareRegression())
           .fit(traj).model_.connection(phi)}
    out.update({f"model_{k}": v for k, v in models.items()})
    out.update(zip(("bin_centres", "bin_mean", "bin_rms", "bin_se"),
                   phase_bin_errors(models["data_driven"], models["ground_truth"],
                                    prep.phase, 24), strict=True))
    return out


@pytest.mark.parametrize("device", DEVICES)
def test_pipeline_runs_on_the_inputs_device(device):
    traj = _data(device)
    assert traj.pose.device.type == device and traj.power.device.type == device
    for name, value in _pipeline(traj, NLinkSwimmer(3)).items():
        assert value.device.type == device, name
        assert torch.isfinite(value).all(), name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_fits_of_the_same_data_agree():
    # CPU and CUDA draw different random numbers: simulate once, fit the same data on both.
    traj = _data("cpu")
    est_cpu = ConnectionEstimator().fit(traj)
    est_gpu = ConnectionEstimator().fit(traj.to("cuda"))
    phi = torch.linspace(0, 2 * np.pi, 33, dtype=torch.float64)
    a_cpu = est_cpu.model_.connection(phi)
    a_gpu = est_gpu.model_.connection(phi.cuda()).cpu()
    rel = (a_gpu - a_cpu).abs().max() / a_cpu.abs().max()
    assert rel < 1e-10, float(rel)


class _NoDefaultDevice(TorchFunctionMode):
    """Fails on any tensor made on the default device (``meta`` here) or via NumPy."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func is torch.from_numpy:
            raise AssertionError("torch.from_numpy on the pipeline's path (a CPU round trip)")
        if (func in (torch.as_tensor, torch.asarray) and args
                and isinstance(args[0], torch.Tensor) and "device" not in kwargs):
            kwargs["device"] = args[0].device  # as CUDA would: a tensor keeps its device
        out = func(*args, **kwargs)
        for o in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(o, torch.Tensor) and o.device.type == "meta":
                raise AssertionError(f"{getattr(func, '__name__', func)} made a tensor on the "
                                     "default device instead of the inputs' device")
        return out


def test_no_tensor_is_made_on_the_default_device():
    eta = torch.tensor(0.025, dtype=torch.float64)
    system, gait = NLinkSwimmer(3), reference_gait("3link")
    with torch.device("meta"), _NoDefaultDevice():
        traj = simulate(system, gait, eta=eta, n_cycles=12, seeds=SEEDS)
        traj = observe(traj, 0.002, seeds=SEEDS)
        out = _pipeline(traj, system)
    assert all(v.device.type == "cpu" for v in out.values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sweep_cell_runs_on_cuda():
    from torchconn.sweep.config import load_config
    from torchconn.sweep.experiment import experiment_cells, run_cell

    config = load_config("quick", ["simulation.n_cycles=8", "experiment.trials=4"])
    cell = experiment_cells(config.experiments[0], 4)[0]
    rows = run_cell(config, cell, device="cuda").results
    assert rows and all(np.isfinite(row[-1]) for row in rows)
