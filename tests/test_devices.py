"""The pipeline follows its inputs' device.

simulate -> observe -> ConnectionEstimator().fit -> evaluation models -> ``evaluate_gait``, and
the discrepancy workflow (``diagnose``), on every available device (CUDA when present, skipped
otherwise), and, on any machine, a guard that no tensor on the path is created on torch's
default device instead of the inputs' one: the pipeline, a small diagnosis, one round of the
improvement loop and a sweep cell run on CPU inputs with the default device set to ``meta``,
so a factory call without ``device=`` (``torch.zeros(n)``, ``torch.tensor(list)``, ...) yields a
``meta`` tensor and fails the test. That is exactly the tensor that would land on the CPU beside
CUDA inputs. The commands' ``--device`` flag is checked here too.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression, observe, simulate
from torchconn._cli import InputError, resolve_device
from torchconn.discrepancy import DiscrepancySettings, diagnose, simulate_with_effects
from torchconn.evaluation.models import (
    clean_trajectory,
    error_summary,
    phase_bin_errors,
    reference_models,
)
from torchconn.improve import LoopSettings, TrustRegion, circle_gait, improve
from torchconn.physics.gaits import FourierGait, reference_gait

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                  reason="needs CUDA")),
]
SEEDS = np.arange(4)
#: a small diagnosis: one candidate (an ambient flow that is there), no term-by-term table
FLOW = {"ambient_flow": {"u_x": 0.01, "u_y": -0.005}}
DIAGNOSIS = DiscrepancySettings(candidates=("ambient_flow",), compare_terms=False, n_folds=3,
                                n_boot=20)


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
    # a gait near the fitted cycle: the first-order prediction with redrawn models
    near = _nearby_gait(est.model_)
    pred = est.model_.evaluate_gait(near, phase_offset=0.0, n_draws=8, n_steps=64)
    out.update(gait_displacement=pred.displacement, gait_se=pred.displacement_se,
               gait_draws=pred.draws, gait_excursion=pred.excursion)
    return out


def _nearby_gait(model) -> FourierGait:
    """The mean fitted cycle of ``model`` with its first harmonic 2 % larger."""
    c = model.gamma.coeffs.detach().reshape(-1, *model.gamma.coeffs.shape[-2:]).mean(0)
    c = c.clone()
    c[1:3] *= 1.02
    return FourierGait(c)


def _diagnosis(device: str, system, gait):
    """A short recording with an ambient flow, and its diagnosis: every output tensor."""
    eta = torch.tensor(0.025, dtype=torch.float64, device=device)
    traj = simulate_with_effects(system, gait, FLOW, eta=eta, n_cycles=8, seeds=[1, 2],
                                 omega=0.002)
    report = diagnose(traj, system, DIAGNOSIS)
    final = report.fits["final"]
    return report, {"recording": traj.pose, "p": final.p, "cov": final.cov, "rho": final.rho,
                    "J": final.J, "sse_cv": final.sse_cv, "floor": report.fits["problem"].weight,
                    "xi": report.fits["measurement"].xi}


@pytest.mark.parametrize("device", DEVICES)
def test_pipeline_runs_on_the_inputs_device(device):
    traj = _data(device)
    assert traj.pose.device.type == device and traj.power.device.type == device
    for name, value in _pipeline(traj, NLinkSwimmer(3)).items():
        assert value.device.type == device, name
        assert torch.isfinite(value).all(), name


@pytest.mark.parametrize("device", DEVICES)
def test_diagnosis_runs_on_the_inputs_device(device):
    report, out = _diagnosis(device, NLinkSwimmer(3), reference_gait("3link"))
    assert report.verdict == "effect", report.summary()
    assert [e.name for e in report.effects] == ["ambient_flow"]
    assert report.data["device"].startswith(device)
    for name, value in out.items():
        assert value.device.type == device, name
        assert torch.isfinite(value).all(), name


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.cpu() - b.cpu()).abs().max() / b.cpu().abs().max().clamp_min(1e-300))


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
    # the gait prediction from the two fits (no redraws: CPU and CUDA draw different numbers)
    near = _nearby_gait(est_cpu.model_)
    d_cpu = est_cpu.model_.evaluate_gait(near, phase_offset=0.0, n_draws=0).displacement
    d_gpu = est_gpu.model_.evaluate_gait(near, phase_offset=0.0, n_draws=0).displacement
    assert d_gpu.device.type == "cuda"
    assert _relative(d_gpu, d_cpu) < 1e-10


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_diagnoses_of_the_same_data_agree():
    system = NLinkSwimmer(3)
    traj = simulate_with_effects(system, reference_gait("3link"), FLOW, eta=0.025,
                                 n_cycles=8, seeds=[1, 2], omega=0.002)
    phase = traj.truth.phase  # the same cycles and folds on both devices
    cpu = diagnose(traj, system, DIAGNOSIS, phase=phase)
    gpu = diagnose(traj.to("cuda"), system, DIAGNOSIS, phase=phase.cuda())
    assert gpu.fits["final"].p.device.type == "cuda"
    assert cpu.verdict == gpu.verdict == "effect"
    # the prepared measurement, the noise floor, and the residual and its forward-mode
    # Jacobian at the same parameters: the same numbers on both devices
    m_cpu, m_gpu = cpu.fits["measurement"], gpu.fits["measurement"]
    assert torch.equal(m_gpu.mask.cpu(), m_cpu.mask)
    assert _relative(m_gpu.xi, m_cpu.xi) < 1e-10
    assert _relative(gpu.fits["problem"].weight, cpu.fits["problem"].weight) < 1e-10
    p = cpu.fits["final"].p
    rho_cpu, J_cpu = cpu.fits["problem"].evaluate(["ambient_flow"], p)
    rho_gpu, J_gpu = gpu.fits["problem"].evaluate(["ambient_flow"], p.cuda())
    assert _relative(rho_gpu, rho_cpu) < 1e-10 and _relative(J_gpu, J_cpu) < 1e-10
    # the fits: Levenberg-Marquardt stops on a cost tolerance, so a last-bit difference may
    # end it one step apart; the parameters agree to a tiny fraction of their standard errors
    se = cpu.fits["final"].se()
    assert ((gpu.fits["final"].p.cpu() - p).abs() <= 1e-3 * se).all()


#: torch.optim makes its own scalars (Adam's ``step`` counter, ``torch.tensor(0.0)`` in torch
#: 2.11) on the default device, which torch keeps on the CPU by design: not ours to move
_TORCH_OPTIM = os.sep + os.path.join("torch", "optim") + os.sep


def _called_from_torch_optim() -> bool:
    """Whether the torch call being checked was made by code in ``torch/optim``: the first
    caller frame outside torch's own dispatch (this mode, ``torch.overrides``, the device
    context)."""
    frame = sys._getframe(2)  # the caller of __torch_function__
    while frame is not None and frame.f_code.co_filename.endswith(
            (os.path.join("torch", "overrides.py"), os.path.join("torch", "utils", "_device.py"))):
        frame = frame.f_back
    return frame is not None and _TORCH_OPTIM in frame.f_code.co_filename


class _NoDefaultDevice(TorchFunctionMode):
    """Fails on any tensor made on the default device (``meta`` here) or via NumPy, but for
    torch.optim's own scalars, which are made on the CPU as torch's real default would."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if _called_from_torch_optim():
            with torch.device("cpu"):  # where torch keeps them with the default device unset
                return func(*args, **kwargs)
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


def test_the_guard_spares_torch_optims_own_scalars_only():
    # torch 2.11's Adam makes its step counter with torch.tensor(0.0) and no device; the same
    # call from any other file must still fail the guard
    code = "def make():\n    return torch.tensor(0.0)\n"
    optim, ours = {"torch": torch}, {"torch": torch}
    exec(compile(code, os.path.join(os.sep, "site", "torch", "optim", "adam.py"), "exec"), optim)
    exec(compile(code, os.path.join(os.sep, "src", "torchconn", "fit.py"), "exec"), ours)
    with torch.device("meta"), _NoDefaultDevice():
        assert optim["make"]().device.type == "cpu"
        with pytest.raises(AssertionError, match="default device"):
            ours["make"]()


def test_no_tensor_is_made_on_the_default_device():
    eta = torch.tensor(0.025, dtype=torch.float64)
    system, gait = NLinkSwimmer(3), reference_gait("3link")
    with torch.device("meta"), _NoDefaultDevice():
        traj = simulate(system, gait, eta=eta, n_cycles=12, seeds=SEEDS)
        traj = observe(traj, 0.002, seeds=SEEDS)
        out = _pipeline(traj, system)
    assert all(v.device.type == "cpu" for v in out.values())


def test_no_tensor_is_made_on_the_default_device_in_a_diagnosis():
    system, gait = NLinkSwimmer(3), reference_gait("3link")
    with torch.device("meta"), _NoDefaultDevice():
        report, out = _diagnosis("cpu", system, gait)
    assert report.verdict == "effect", report.summary()
    assert all(v.device.type == "cpu" for v in out.values())


def test_no_tensor_is_made_on_the_default_device_in_an_improvement_round():
    # every step of a round (record, measure, fit, propose, predict), with a short optimisation
    settings = LoopSettings(rounds=1, trials=2, cycles=12, seed=3,
                            trust_region=TrustRegion(scale=3.0, steps=20))
    system, start = NLinkSwimmer(3), circle_gait(2, 0.5)
    with torch.device("meta"), _NoDefaultDevice():
        res = improve(system, start, settings)
    (rnd,) = res.rounds
    assert rnd.proposal.coeffs.device.type == "cpu"
    assert np.isfinite([rnd.observed, rnd.predicted, rnd.realised]).all()


def test_no_tensor_is_made_on_the_default_device_in_a_sweep_cell(monkeypatch):
    from torchconn.sweep import experiment
    from torchconn.sweep.config import load_config
    from torchconn.sweep.experiment import experiment_cells, run_cell

    config = load_config("quick", ["simulation.n_cycles=8", "experiment.trials=4"])
    cell = experiment_cells(config.experiments[0], 4)[0]
    # the swimmer and the gait are built from numbers (on the default device, like any
    # constructor without tensors) and follow the data when evaluated: build them outside
    system, gait = experiment.make_system("3link"), reference_gait("3link")
    monkeypatch.setattr(experiment, "make_system", lambda name: system)
    monkeypatch.setattr(experiment, "reference_gait", lambda name: gait)
    with torch.device("meta"), _NoDefaultDevice():
        rows = run_cell(config, cell).results
    assert rows and all(np.isfinite(row[-1]) for row in rows)


# ============================================================================ --device
def test_device_names_are_checked_against_this_machine():
    assert resolve_device("cpu") == torch.device("cpu")
    for bad in ("gpu", "cpu:0", "cuda:x", "", 3):
        with pytest.raises(InputError, match="unknown device; expected cpu, cuda, cuda:N or mps"):
            resolve_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match=r"^--device cuda: CUDA is not available on this "
                                             r"machine \(torch "):
            resolve_device("cuda")
    else:
        n = torch.cuda.device_count()
        assert resolve_device(f"cuda:{n - 1}") == torch.device(f"cuda:{n - 1}")
        with pytest.raises(InputError, match=f"this machine has {n} CUDA device"):
            resolve_device(f"cuda:{n}")
    with pytest.raises(InputError, match="^--device mps: "):  # unavailable, or without float64
        resolve_device("mps")


@pytest.mark.parametrize("command", ["sweep", "fit", "discrepancy", "improve"])
def test_commands_refuse_an_unknown_device_in_one_line(command, tmp_path, capsys):
    from torchconn.discrepancy.__main__ import main as discrepancy
    from torchconn.fit import main as fit
    from torchconn.improve.__main__ import main as improve_main
    from torchconn.sweep.__main__ import main as sweep

    data = tmp_path / "missing.csv"  # never read: the device is checked first
    out = ["--out", str(tmp_path / "out")]
    argv = {"sweep": (sweep, ["--config", "quick", *out]),
            "fit": (fit, [str(data), "--links", "3", *out]),
            "discrepancy": (discrepancy, [str(data), "--links", "3", *out]),
            "improve": (improve_main, ["simulate", "--rounds", "1", *out])}
    main, args = argv[command]
    assert main([*args, "--device", "tpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--device 'tpu': unknown device; expected cpu, cuda, cuda:N" in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is present")
def test_sweep_refuses_cuda_without_it(tmp_path, capsys):
    from torchconn.sweep.__main__ import main as sweep

    assert sweep(["--config", "quick", "--out", str(tmp_path), "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert f"--device cuda: CUDA is not available on this machine (torch {torch.__version__})" \
        in err


def test_the_sweep_device_is_in_the_config_and_the_cells_fingerprint(monkeypatch):
    from torchconn.sweep import config as config_module
    from torchconn.sweep.experiment import experiment_cells
    from torchconn.sweep.runner import cell_fingerprint

    with pytest.raises(InputError, match="device 'tpu': unknown device"):
        config_module.load_config("quick", ["device=tpu"])
    cpu = config_module.load_config("quick")
    assert cpu.device == "cpu"
    cell = experiment_cells(cpu.experiments[0], 4)[0]
    # pretend CUDA is here: a cell computed on it must never be reused for a CPU run
    monkeypatch.setattr(config_module, "resolve_device", lambda name, where: torch.device(name))
    cuda = config_module.load_config("quick", ['device="cuda:1"'])
    assert cuda.device == "cuda:1" and cuda.fingerprint(cuda.experiments[0])["device"] == "cuda"
    assert cell_fingerprint(cuda, cell) != cell_fingerprint(cpu, cell)
    cuda0 = config_module.load_config("quick", ["device=cuda"])
    assert cell_fingerprint(cuda0, cell) == cell_fingerprint(cuda, cell)  # one type, one stream
