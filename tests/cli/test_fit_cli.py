"""``python -m torchconn.fit`` on CSV recordings in the trajectory file format."""

from __future__ import annotations

import csv
import json
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.fit import main
from torchconn.fit import main as fit_main
from torchconn.io.trajectory_files import read_csv, write_csv
from torchconn.physics.gaits import reference_gait
from torchconn.regression.estimator import ConnectionEstimator
from torchconn.regression.model import LocalConnectionModel
from torchconn.simulation.observe import observe

from ..recordings import five_link_a_error


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    seeds = np.array([3, 4])
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=20,
                    seeds=seeds)
    traj = observe(traj, 0.0, dropout=0.02, seeds=seeds)  # marker drop-outs, no jitter
    path = tmp_path_factory.mktemp("data") / "trials.csv"
    write_csv(traj, path)
    return path


def test_fit_writes_model_table_and_plots(recording, tmp_path):
    out = tmp_path / "fit"
    assert main([str(recording), "--links", "3", "--out", str(out), "--grid", "50"]) == 0
    with (out / "connection.csv").open() as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    expected = (["phase", "r1", "r2"] + [f"A_{k}_{i}" for k in ("x", "y", "theta") for i in (1, 2)]
                + [f"dA_{k}_{i}_{j}" for k in ("x", "y", "theta") for i in (1, 2) for j in (1, 2)]
                + [f"M_{i}_{j}" for i in (1, 2) for j in (1, 2)]
                + ["M_gamma_dot_1", "M_gamma_dot_2", "power_on_cycle"])
    # each estimate's standard error after all the estimates
    assert header == expected + [f"{c}_se" for c in expected[3:]]
    assert len(rows) == 51
    table = np.array(rows[1:], dtype=float)
    # the fitted connection along the fitted cycle is close to the simulator's there
    swimmer = NLinkSwimmer(3)
    a_true = swimmer.connection(torch.tensor(table[:, 1:3])).reshape(50, -1).numpy()
    assert np.abs(table[:, 3:9] - a_true).max() < 0.03
    model = LocalConnectionModel.load(out / "model.npz")
    assert model.batch_shape == ()
    settings = model.meta["settings"]  # the estimator's full settings travel with the model
    assert settings["cycle"]["order"] == 8 and settings["regression"]["n_bins"] == 48
    assert settings["pool"] is True and settings["phaser"]["method"] == "phaser"
    # M̂γ̇ and the on-cycle power against the swimmer's exact metric on the fitted cycle
    phi = torch.tensor(table[:, 0])
    gd = model.gamma_dot_at(phi)
    m_true = swimmer.metric(torch.tensor(table[:, 1:3]))
    mgd_true = (m_true @ gd[..., None])[..., 0].numpy()
    p_true = (gd.numpy() * mgd_true).sum(-1)
    end = len(expected)  # the estimates' columns, before their standard errors
    assert np.sqrt(((table[:, end - 3:end - 1] - mgd_true) ** 2).sum(-1).mean()
                   / (mgd_true**2).sum(-1).mean()) < 0.02
    assert np.sqrt(((table[:, end - 1] - p_true) ** 2).mean() / (p_true**2).mean()) < 0.01
    # the 95% bands (±1.96 SE) cover the simulator's A along most of the cycle
    a_se = table[:, end:end + 6]
    assert (a_se > 0).all() and (np.abs(table[:, 3:9] - a_true) < 1.96 * a_se).mean() > 0.8
    for name in ("held_out_velocity.png", "connection.png", "limit_cycle.png", "metric.png"):
        assert (out / name).stat().st_size > 1000
    sidecar = json.loads((out / "fit.json").read_text())
    assert sidecar["device"] == "cpu"  # the default
    assert sidecar["model"] == {"window": model.meta["window"], "metric": True}


def test_fit_rejects_the_wrong_number_of_links(recording, tmp_path, capsys):
    assert main([str(recording), "--links", "5", "--out", str(tmp_path / "x")]) == 2
    assert "joint" in capsys.readouterr().err


def test_fit_takes_any_stage_setting_and_refuses_bad_ones_by_name(recording, tmp_path, capsys):
    for extra, message in (
        (["--set", "regression.kernal=box"], "unknown key 'kernal' (did you mean 'kernel'?)"),
        (["--set", "smoother.order=4"], "RTSSmoother.order must be one of 2, 3, got 4"),
        (["--set", "estimator.phasr.order=2"],
         "unknown key 'phasr' (did you mean 'phaser'?)"),
        (["--n-bins", "2"], "NoiseAwareRegression.n_bins must be >= 3, got 2"),
    ):
        assert main([str(recording), "--links", "3", "--out", str(tmp_path / "x"), *extra]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # refused before anything is read or written
    out = tmp_path / "ok"
    assert main([str(recording), "--links", "3", "--out", str(out), "--set", "cycle.order=7",
                 "--set", "regression.kernel=box"]) == 0
    settings = LocalConnectionModel.load(out / "model.npz").meta["settings"]
    assert settings["cycle"]["order"] == 7 and settings["regression"]["kernel"] == "box"


def test_fit_metric_option(recording, tmp_path, capsys):
    no_power = tmp_path / "no_power.csv"
    lines = recording.read_text().splitlines()
    no_power.write_text("\n".join(",".join(line.split(",")[:-1]) for line in lines) + "\n")
    # asked for without a power column: a clear error, nothing written
    assert main([str(no_power), "--links", "3", "--out", str(tmp_path / "a"),
                 "--metric", "yes"]) == 2
    assert "power" in capsys.readouterr().err
    assert not (tmp_path / "a" / "model.npz").exists()
    # switched off with a power column: the connection alone
    assert main([str(recording), "--links", "3", "--out", str(tmp_path / "b"), "--metric",
                 "no"]) == 0
    assert LocalConnectionModel.load(tmp_path / "b" / "model.npz").M is None


def test_fit_reports_held_out_skill_and_cross_validated_complexity(recording, tmp_path,
                                                                    capsys):
    out = tmp_path / "cv"
    assert main([str(recording), "--links", "3", "--out", str(out), "--regression",
                 "noise_aware", "--complexity", "cv"]) == 0
    text = capsys.readouterr().out
    assert "complexity chosen by held-out error" in text
    # the plain summary's table holds the held-out R² that fit.json records
    assert "How well it predicts cycles it did not see" in text
    assert "phase-averaged velocity" in text
    row = next(line for line in text.splitlines() if line.strip().startswith("this model "))
    held = json.loads((out / "fit.json").read_text())["held_out"]["interleaved"]
    assert [float(x) for x in row.split()[-3:]] == pytest.approx(
        [held[c]["model"] for c in ("v_x", "v_y", "omega")], abs=0.0051)
    assert (out / "report.html").exists()
    model = LocalConnectionModel.load(out / "model.npz")
    assert model.batch_shape == ()
    # the forecasting model is written beside the connection where the two differ, and
    # fit.json and the printout say so
    sidecar = json.loads((out / "fit.json").read_text())
    forecast_file = out / "forecast_model.npz"
    assert forecast_file.exists() == (sidecar["forecast_model"] is not None)
    assert ("forecast_model.npz: the forecasting model" in text) == forecast_file.exists()
    if forecast_file.exists():
        assert sidecar["forecast_model"] == {"file": "forecast_model.npz",
                                             **model.meta["forecast_model"]}
        model = LocalConnectionModel.load(forecast_file)
    # the per-component choice: fit.json, the forecasting model's meta and the printout agree
    chosen = sidecar["complexity"]
    assert chosen["components"] == ["v_x", "v_y", "omega"]
    assert chosen["checked"] is True  # chosen by held-out error
    fallback = chosen["phase_averaged"]
    assert len(fallback) == 3 and all(isinstance(x, bool) for x in fallback)
    assert model.meta.get("phase_averaged", [False] * 3) == fallback
    assert ("predicted by the phase-averaged velocity" in text) == any(fallback)
    conn = chosen["connection_only"]
    assert len(conn) == 3 and all(isinstance(x, bool) for x in conn)
    assert model.meta.get("connection_only", [False] * 3) == conn
    assert ("predicted by the connection alone" in text) == any(conn)


def _fit_nine_link_three_cycles(tmp_path, *options):
    """``torchconn-fit`` of the 9-link reference gait, 3 cycles, ω = 0.005 (as in
    test_held_out), where no model with the offset terms can be fitted without a third of the
    cycles, with the command-line ``options``; its output folder."""
    seeds = np.array([11])
    spc = 126
    clean = simulate(NLinkSwimmer(9), reference_gait("9link"), eta=0.025, n_cycles=4,
                     samples_per_cycle=spc, seeds=seeds)
    traj = observe(clean, 0.005, seeds=seeds).with_fields(power=None)
    path = tmp_path / "short.csv"
    write_csv(traj.slice_time(0, 3 * spc + 1), path)
    out = tmp_path / "fit"
    # 3 cycles tracked come out as 2.95 by the preflight's count: the user's own minimum for
    # the phase estimate is the fit's rule
    assert main([str(path), "--links", "9", "--out", str(out), "--set",
                 "phaser.min_cycles=2.5", "--no-figures", *options]) == 0
    return out


def test_fit_says_when_the_connection_alone_was_checked(tmp_path, capsys):
    """The 3-cycle 9-link recording: the connection alone is checked in place of the full
    model; the printout, fit.json and model.npz say so."""
    out = _fit_nine_link_three_cycles(tmp_path)
    text = capsys.readouterr().out
    assert "the connection alone (1 + d regressors per bin) was fitted and checked" in text
    assert "no held-out check can score it" not in text
    chosen = json.loads((out / "fit.json").read_text())["complexity"]
    assert chosen["checked"] is True and chosen["connection_regressed"] is True
    model = LocalConnectionModel.load(out / "model.npz")
    assert model.meta["connection_regressed"] is True
    assert bool((model.dA.coeffs == 0).all()) and bool((model.A.coeffs != 0).any())
    conn = chosen["connection_only"]
    assert ("forecasts predict by the connection alone (it beat" in text) == any(conn)


def test_fit_says_when_no_held_out_check_can_score_a_short_recording(tmp_path, capsys,
                                                                      monkeypatch):
    """Where not even the connection alone can be scored (made so here), the printout,
    fit.json and the model say the fit stood unchecked and which components the phase
    average predicts."""
    from torchconn.regression import selection

    def unscored(*args, **kw):
        raise ValueError("select_connection_alone: no candidate could be fitted")

    monkeypatch.setattr(selection, "select_connection_alone", unscored)
    # no physics prior: this simulation is of its reference family, which would take over
    # the forecasts examined here
    out = _fit_nine_link_three_cycles(tmp_path, "--prior", "none")
    text = capsys.readouterr().out
    assert "fit needs 2.5 cycles per trial and 2.5 in all: ok" in text
    assert "no held-out check can score it" in text
    assert "complexity chosen by held-out error" not in text
    assert "are predicted by the phase-averaged velocity" in text
    chosen = json.loads((out / "fit.json").read_text())["complexity"]
    assert chosen["checked"] is False
    assert chosen["phase_averaged"] == [True, True, True]
    # model.npz (and connection.csv) hold the connection estimated at the given complexity;
    # forecast_model.npz the phase average everywhere, and the printout tells them apart
    assert "model.npz, connection.csv and the plots: the connection, every row estimated" in text
    assert "forecast_model.npz: the forecasting model" in text
    model = LocalConnectionModel.load(out / "model.npz")
    assert "phase_averaged" not in model.meta and bool((model.A.coeffs != 0).any())
    assert model.meta["forecast_model"] == {"n_bins": 48, "fourier_order": 12, "A_ridge": 0.0,
                                            "phase_averaged": [True, True, True],
                                            "connection_only": None, "prior_weight": None}
    table = np.loadtxt(out / "connection.csv", delimiter=",", skiprows=1)
    assert np.abs(table[:, 1 + 8:1 + 8 + 3 * 8]).max() > 0  # A's columns
    forecast = LocalConnectionModel.load(out / "forecast_model.npz")
    assert forecast.meta["phase_averaged"] == [True, True, True]
    assert bool((forecast.A.coeffs == 0).all())
    assert json.loads((out / "fit.json").read_text())["outputs"][:3] == [
        "model.npz", "connection.csv", "forecast_model.npz"]


def test_fit_tells_the_connection_from_the_forecasts_when_a_ridge_is_chosen(tmp_path, capsys):
    """5-link travelling wave, 3 cycles, ω = 0.005 (seed 32): held-out error chooses a ridge
    that penalises A for the forecasts, so model.npz holds the connection chosen and fitted
    with A unpenalised and forecast_model.npz the forecasts; the printout names both."""
    import math

    from torchconn.physics.gaits import FourierGait
    from torchconn.regression.estimator import estimator_from_settings

    lag = torch.arange(4, dtype=torch.float64) * (math.pi / 2)
    coeffs = torch.zeros(3, 4, dtype=torch.float64)
    coeffs[1], coeffs[2] = 0.7 * torch.cos(lag), 0.7 * torch.sin(lag)
    seeds = np.array([32])
    clean = simulate(NLinkSwimmer(5), FourierGait(coeffs), eta=0.025, n_cycles=3,
                     samples_per_cycle=126, seeds=seeds)
    path = tmp_path / "short.csv"
    write_csv(observe(clean, 0.005, seeds=seeds).with_fields(power=None), path)
    out = tmp_path / "fit"
    assert main([str(path), "--links", "5", "--out", str(out), "--no-figures", "--set",
                 "phaser.min_cycles=2.5"]) == 0
    text = capsys.readouterr().out
    model = LocalConnectionModel.load(out / "model.npz")
    forecast = LocalConnectionModel.load(out / "forecast_model.npz")
    differs, own = model.meta["forecast_model"], model.meta["settings"]["regression"]
    assert differs["A_ridge"] > 0 and own["ridge_connection"] is False
    assert forecast.meta["settings"]["regression"]["ridge_connection"] is True
    assert (f"the connection, every row estimated ({own['n_bins']} bins, Fourier order "
            f"{own['fourier_order']}, ridge {own['ridge']:g} on b and dA/dr only, A "
            "unpenalised") in text
    assert f"A shrunk by the ridge {differs['A_ridge']:g}" in text
    assert "How well it predicts cycles it did not see" in text
    # model.npz is the fit of the settings it records, on the estimator's own data
    est = estimator_from_settings(model.meta["settings"])
    assert est.regression.ridge_connection is False
    assert json.loads((out / "fit.json").read_text())["forecast_model"]["file"] == \
        "forecast_model.npz"


def test_fit_names_the_components_that_lose_to_the_phase_average(tmp_path, capsys):
    # 6 noisy cycles at the fixed 48 bins / order 12: the model loses held out somewhere, and
    # the printout names each such component with both R² (fit.json's numbers)
    seeds = np.array([3, 4])
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=6,
                    seeds=seeds)
    path = tmp_path / "short.csv"
    write_csv(observe(traj, 0.01, seeds=seeds), path)
    out = tmp_path / "fit"
    assert main([str(path), "--links", "3", "--out", str(out), "--complexity", "fixed",
                 "--metric", "no"]) == 0
    printed = capsys.readouterr()
    text = printed.err
    held = json.loads((out / "fit.json").read_text())["held_out_skill"]
    losing = [k for k, worse in enumerate(held["worse_than_phase_average"]) if worse]
    assert losing, "this recording was chosen because its fixed-complexity model loses"
    # warnings go to stderr in the one format of every command, never to stdout
    warning = next(line for line in text.splitlines()
                   if line.startswith("torchconn-fit: warning: the model"))
    assert "warning" not in printed.out.lower()
    for k, name in enumerate(held["components"]):
        shown = (f"{name} (held-out R² {held['model'][k]:.3f} vs phase average "
                 f"{held['phase_average'][k]:.3f})")
        assert (shown in warning) == (k in losing), (shown, warning)
    # every component has skill here, so nothing is called unpredictable
    assert held["without_skill"] == [False, False, False]
    assert "warning: neither the model" not in text


def test_more_bins_than_samples_is_refused_before_any_allocation(recording, tmp_path, capsys):
    # the bins' series grow as n_bins²: 100000 bins on this recording once took all memory
    for complexity in ("fixed", "auto"):
        assert main([str(recording), "--links", "3", "--out", str(tmp_path / "x"), "--n-bins",
                     "100000", "--complexity", complexity, "--no-figures"]) == 2
        err = capsys.readouterr().err
        assert "n_bins = 100000 is more than the" in err and "--n-bins" in err


F64 = torch.float64


PHI = torch.linspace(0, 2 * math.pi, 49, dtype=F64)[:-1]


def test_the_command_fits_recordings_of_different_lengths(unequal_recordings, tmp_path, capsys):
    # the reported crash: 'stack expects each tensor to be equal size' from the phase stage
    out = tmp_path / "pooled"
    assert fit_main([str(f) for f in unequal_recordings] + ["--links", "5", "--out", str(out),
                                               "--no-figures"]) == 0
    assert "3 trial(s)" in capsys.readouterr().out
    model = LocalConnectionModel.load(out / "model.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        api = ConnectionEstimator(pool=True).fit(read_csv(unequal_recordings)).model_
    # the command's default is the pooled fit of the API
    torch.testing.assert_close(model.connection(PHI), api.connection(PHI), rtol=0, atol=1e-12)
    # one model per trial: the command writes one model, so it is run on each file
    for k in (0, 2):  # the shortest, its first samples lost; the longest, its last
        out = tmp_path / f"trial{k}"
        assert fit_main([str(unequal_recordings[k]), "--links", "5", "--out", str(out), "--no-figures",
                         "--metric", "no", "--set", "estimator.pool=false"]) == 2
        assert "estimator.pool = false" in capsys.readouterr().err and not out.exists()
        assert fit_main([str(unequal_recordings[k]), "--links", "5", "--out", str(out), "--no-figures",
                         "--metric", "no"]) == 0
        model = LocalConnectionModel.load(out / "model.npz")
        assert model.batch_shape == () and float(five_link_a_error(model)) < 0.45


def test_connection_csv_standard_errors_are_the_plotted_bands_between_bins(recording, tmp_path):
    """The ``_se`` columns are the per-bin standard errors the plots draw (±1.96 SE), at the
    bin centres themselves and linearly (periodically) between them."""
    from torchconn.fit import connection_table

    out = tmp_path / "fit"
    assert main([str(recording), "--links", "3", "--out", str(out), "--no-figures",
                 "--quiet"]) == 0
    assert (out / "connection.csv").read_text().splitlines()[0].split(",")[-1] \
        == "power_on_cycle_se"
    model = LocalConnectionModel.load(out / "model.npz")
    bins = model.bins
    n_bins = bins.phase.shape[0]
    # the bins are centred on k 2π/M: a grid of 2M rows has them on its even rows
    assert torch.allclose(bins.phase, torch.arange(n_bins, dtype=torch.float64)
                          * (2 * math.pi / n_bins))
    cols, rows = connection_table(model, 2 * n_bins)
    table = torch.tensor(rows, dtype=torch.float64)
    for name, se in (("A_y_2_se", bins.A_se[:, 1, 1]), ("dA_theta_1_2_se", bins.dA_se[:, 2, 0, 1]),
                     ("M_1_1_se", bins.M_se[:, 0, 0]),
                     ("M_gamma_dot_2_se", bins.M_gamma_dot_se[:, 1]),
                     ("power_on_cycle_se", bins.power_on_cycle_se)):
        got = table[:, cols.index(name)]
        assert bool((se > 0).all()), name
        assert torch.allclose(got[0::2], se, rtol=1e-9), name
        assert torch.allclose(got[1::2], (se + se.roll(-1)) / 2, rtol=1e-9), name


def test_fit_json_gives_the_gait_frequency_in_hz_and_the_units(recording, tmp_path):
    """The gait frequency comes from the recording's time base: the same recording with its
    clock in seconds at 1.5 cycles per second gives 1.5 Hz."""
    traj = read_csv(recording)
    hz = 1.5
    # the simulation's clock runs one cycle per 2π time units: rescale it to seconds
    t = traj.t / (2 * math.pi * hz)
    path = write_csv(traj.with_fields(t=t), tmp_path / "seconds.csv")
    out = tmp_path / "fit"
    assert main([str(path), "--links", "3", "--out", str(out), "--no-figures", "--quiet",
                 "--metric", "no"]) == 0
    record = json.loads((out / "fit.json").read_text())
    gait = record["gait"]
    assert gait["frequency_hz"] == pytest.approx(hz, rel=0.01)
    assert gait["period_s"] == pytest.approx(1 / gait["frequency_hz"])
    assert gait["phase_rate"] == pytest.approx(2 * math.pi * gait["frequency_hz"])
    units = record["units"]
    assert units["t, dt, period_s"] == "s" and units["v_x, v_y"] == "body lengths/s"
    assert record["data"]["dt"] == pytest.approx(float(t[1] - t[0]))
