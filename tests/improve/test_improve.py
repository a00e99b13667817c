"""Proposals, the trust region, the improvement loop and its command, and gait export."""

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, simulate
from torchconn.improve import (
    LoopSettings,
    TrustRegion,
    ceiling,
    circle_gait,
    exact_local_model,
    improve,
    measure_cycles,
    propose_gait,
    true_objective,
)
from torchconn.improve.export import gait_table, write_gait
from torchconn.physics.gaits import FourierGait, evaluate

from ..recordings import wobbled_gait


def test_propose_improves_and_stays_in_trust_region(fitted_3link):
    system, _, model = fitted_3link
    tr = TrustRegion(scale=2.0)
    prop = propose_gait(model, "displacement", tr, n_draws=32)
    assert prop.step <= prop.radius * (1 + 1e-9)
    assert prop.gain > 0 and prop.gain_se > 0
    assert abs(float(prop.prediction.displacement[2])) < tr.max_turn + 0.01  # goes straight
    base_true = true_objective(system, FourierGait(model.gamma.coeffs), "displacement")
    assert true_objective(system, prop.gait, "displacement") > base_true


def test_one_loop_round_improves_realised_displacement():
    system = NLinkSwimmer(3)
    start = circle_gait(2, 0.5)
    res = improve(system, start, LoopSettings(rounds=1, trials=2, cycles=15, seed=3))
    (rnd,) = res.rounds
    assert rnd.realised > res.start_true * 1.3
    assert rnd.cycles_used == 30
    assert abs(rnd.observed - rnd.true) < 4 * rnd.observed_se + 0.05 * rnd.true


def test_measure_cycles_matches_the_noise_free_gait():
    system = NLinkSwimmer(3)
    gait = circle_gait(2, 1.0)
    traj = simulate(system, gait, eta=0.0, alpha=0.05, n_cycles=4, seeds=np.arange(2),
                    stationary_start=False)
    m = measure_cycles(traj)
    true = evaluate(system, gait).displacement
    assert m.planar == pytest.approx(float(torch.linalg.vector_norm(true[:2])), rel=2e-3)
    assert m.n_cycles == 2 * 3  # the last period is one sample short


def test_proposal_outside_trust_region_is_refused(fitted_3link):
    from torchconn.improve.propose import check_trust_region

    _, _, model = fitted_3link
    tr = TrustRegion(radius=0.1)
    check_trust_region(model, wobbled_gait(FourierGait(model.gamma.coeffs), 0.05), tr)
    with pytest.raises(ValueError, match="trust region"):
        check_trust_region(model, wobbled_gait(FourierGait(model.gamma.coeffs), 0.5), tr)


def test_model_without_shape_derivative_is_refused(fitted_3link):

    _, _, model = fitted_3link
    broken = dataclasses.replace(model, dA=None)
    with pytest.raises(ValueError, match="∂Â/∂r"):
        broken.evaluate_gait(FourierGait(model.gamma.coeffs), phase_offset=0.0)
    with pytest.raises(ValueError, match="∂Â/∂r"):
        propose_gait(broken)


def test_efficiency_without_power_column_is_refused(fitted_3link):
    _, _, model = fitted_3link
    with pytest.raises(ValueError, match="power"):
        propose_gait(model, "efficiency")
    with pytest.raises(ValueError, match="objective must be one of"):
        propose_gait(model, "speed")


def test_efficiency_objective_on_clean_data_with_power(fitted_3link):
    system, traj, _ = fitted_3link
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ConnectionEstimator(pool=True).fit(traj).model_
    prop = propose_gait(model, "efficiency", TrustRegion(scale=1.0), n_draws=16)
    assert math.isfinite(prop.gain) and prop.prediction.efficiency is not None
    assert measure_cycles(traj).efficiency is not None


def test_export_round_trips(tmp_path, fitted_3link):
    _, _, model = fitted_3link
    gait = FourierGait(model.gamma.coeffs)
    table = gait_table(gait, samples_per_cycle=32)
    assert table.shape == (32, 3)
    torch.testing.assert_close(torch.as_tensor(table[:, 1:]), gait(torch.as_tensor(table[:, 0])))
    paths = write_gait(gait, tmp_path / "next")
    import json

    spec = json.loads(paths["json"].read_text())
    back = FourierGait(torch.tensor(spec["fourier_coefficients"], dtype=torch.float64))
    torch.testing.assert_close(back.coeffs, gait.coeffs)


def test_command_proposes_from_recordings(tmp_path):
    from torchconn import write_csv
    from torchconn.improve.__main__ import main

    traj = simulate(NLinkSwimmer(3), circle_gait(2, 0.8), eta=0.025, n_cycles=10,
                    seeds=np.arange(2))
    path = write_csv(traj, tmp_path / "rec.csv")
    assert main(["propose", str(path), "--links", "3", "--out", str(tmp_path / "next")]) == 0
    assert (tmp_path / "next" / "next_gait.csv").exists()
    assert main(["propose", str(tmp_path / "missing.csv"), "--links", "3",
                 "--out", str(tmp_path / "x")]) == 2


@pytest.mark.parametrize("argv, message", [
    (["--threads", "0"], "--threads must be an integer >= 1, got 0"),
    (["--links", "2"], "--links must be >= 3, got 2"),
])
def test_command_errors_are_one_line_through_the_shared_wrapper(argv, message, tmp_path, capsys):
    """Like every torchconn command: ``--threads`` (default 1), one line, exit code 2, nothing
    written."""
    from torchconn.improve.__main__ import main

    out = tmp_path / "out"
    assert main(["simulate", "--rounds", "1", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"torchconn-improve simulate: error: {message}"
    assert not out.exists()


def test_efficiency_proposal_improves_true_efficiency_with_exact_model():
    """The efficiency path end to end where the metric is exact (clean: the exact local model)."""
    system = NLinkSwimmer(3)
    base = circle_gait(2, 1.0)
    model = exact_local_model(system, base, tube_rms=0.08, n_grid=64)
    prop = propose_gait(model, "efficiency", TrustRegion(scale=2.0), n_draws=0)
    before = true_objective(system, base, "efficiency")
    after = true_objective(system, prop.gait, "efficiency")
    assert after > before
    # the model holds M̂ on the cycle only (no ∂M/∂r), so the predicted cost is first-order
    # accurate in ṙ' but zeroth-order in δ: the gain is right in sign and size, not in digits
    assert 0.5 < prop.gain / (after - before) < 2.0


def test_ascent_never_proposes_worse_than_the_fitted_cycle(fitted_3link):
    """The penalties make the projected ascent oscillate: with a step far too long it must still
    return its best iterate -- at worst no change -- never a gait the model predicts worse."""
    _, _, model = fitted_3link
    prop = propose_gait(model, "displacement", TrustRegion(scale=2.0, lr=2.0, steps=15),
                        n_draws=0)
    assert prop.gain >= -1e-12
    assert prop.step <= prop.radius * (1 + 1e-9)


def test_optimiser_respects_the_turning_limit():
    """The ceiling of the loop's own objective: |(x, y)| per cycle of gaits turning at most
    max_turn per cycle. Unconstrained, the 3-link's best planar gaits turn by ~1 rad."""
    from torchconn.physics.gaits.optimize import optimise_gait

    system = NLinkSwimmer(3)
    free = optimise_gait(system, order=2, radius=1.0, component="planar", max_iter=60)
    straight = optimise_gait(system, order=2, radius=1.0, component="planar", max_turn=0.05,
                             max_iter=60)
    turn_free = abs(float(evaluate(system, free.gait).displacement[2]))
    turn = abs(float(evaluate(system, straight.gait).displacement[2]))
    assert turn_free > 0.5
    assert turn < 0.055
    assert straight.x_displacement < free.x_displacement
    with pytest.raises(ValueError, match="max_turn"):
        optimise_gait(system, max_turn=-1.0)


def test_command_proposes_from_several_rounds(tmp_path):
    """``propose CURRENT --earlier EARLIER...``: one model from every round's recordings, centred
    on the current gait, whose wider tube allows a longer step than the current recording's
    alone; the proposal improves the simulator's displacement."""
    import json

    from torchconn import write_csv
    from torchconn.improve.__main__ import main

    system = NLinkSwimmer(3)
    paths = {}
    for name, radius, seed in (("a", 0.5, 0), ("b", 0.6, 1), ("c", 0.7, 2)):
        traj = simulate(system, circle_gait(2, radius), eta=0.025, n_cycles=8,
                        seeds=np.array([seed]))
        paths[name] = str(write_csv(traj, tmp_path / f"{name}.csv"))
    common = ["--links", "3", "--quiet"]
    assert main(["propose", paths["c"], "--out", str(tmp_path / "alone"), *common]) == 0
    assert main(["propose", paths["c"], "--earlier", paths["a"], paths["b"],
                 "--out", str(tmp_path / "pooled"), *common]) == 0
    alone, pooled = (json.loads((tmp_path / d / "report.json").read_text())
                     for d in ("alone", "pooled"))
    assert pooled["trust_radius_rad"] > 1.5 * alone["trust_radius_rad"]
    spec = json.loads((tmp_path / "pooled" / "next_gait.json").read_text())
    gait = FourierGait(torch.tensor(spec["fourier_coefficients"], dtype=torch.float64))
    now = true_objective(system, circle_gait(2, 0.7), "displacement")
    assert true_objective(system, gait, "displacement") > now + 0.5 * pooled["predicted_gain"]


@pytest.mark.slow
def test_three_link_loop_reaches_the_ceiling_in_few_cycles():
    """Issue 36's clean 3-link target (~2-4 min): from a circle of radius 0.5, the default
    loop (recordings of 3 cycles) keeps a gait at >= 90 % of the ceiling (the true connection's
    ascent from the same start in the loop's family and limits) within 15 recorded cycles, and
    the kept gait never falls by more than 2 standard errors."""
    system = NLinkSwimmer(3)
    start = circle_gait(2, 0.5)
    settings = LoopSettings(seed=0, rounds=6)
    res = improve(system, start, settings)
    cap = ceiling(system, "displacement", settings, starts=[start], peaks=(), random_starts=0,
                  max_iter=300).value
    reached = next(r.cycles_used for r in res.rounds if r.kept_true >= 0.9 * cap)
    assert reached <= 15, [(r.cycles_used, r.kept_true / cap) for r in res.rounds]
    for a, b in zip(res.rounds, res.rounds[1:], strict=False):
        assert b.kept_true > a.kept_true - 2 * a.observed_se
