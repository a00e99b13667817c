"""Tracked video in: readers, the converter (checked against the swimmer's own forward
kinematics), gaps, flips, the convert and fit commands, bad input, preflight, known conditions."""

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.convert import main as convert_main
from torchconn.fit import main as fit_main
from torchconn.io.preflight import CYCLE_RULES, CycleRule, preflight
from torchconn.io.tracking import ConversionSettings, TrackingFormatError, convert, read_tracking
from torchconn.known import parse_known, relative_to_known
from torchconn.physics.gaits import reference_gait
from torchconn.simulation.observe import observe
from torchconn.testing.tracking import render_keypoints
from torchconn.trajectory import Trajectory

SAMPLES = Path(__file__).resolve().parents[1] / "data" / "tracking"
NAMES = ("snout", "mid", "tail")
F, K = 5, 3
_f, _k = np.arange(F)[:, None], np.arange(K)[None, :]
#: the points every sample file holds (see tests/data/tracking/make_samples.py)
PTS = np.stack([10.0 + _f + 3 * _k, 20.0 + 2 * _f - _k], -1)


def _wave(d: int):
    k = torch.arange(1, d + 1, dtype=torch.float64)
    return lambda phi: 0.7 * torch.sin(phi[..., None] + 2 * math.pi * k / d)


def _gait(n: int):
    return reference_gait("3link") if n == 3 else reference_gait("9link") if n == 9 else _wave(n - 1)


@pytest.fixture(scope="module")
def sims():
    out = {}
    for n in (3, 5, 9):
        out[n] = simulate(NLinkSwimmer(n), _gait(n), eta=0.025, n_cycles=4, seeds=np.array([7]))
    return out


# ============================================================================ readers
@pytest.mark.parametrize("name", ["sleap.analysis.h5", "sleap.analysis.csv", "dlc.csv",
                                  "dlc_table.h5", "dlc_fixed.h5", "dlc_multi.csv", "worm.wcon",
                                  "points.csv", "points.npz"])
def test_every_reader_parses_its_documented_layout(name):
    pytest.importorskip("h5py") if name.endswith(".h5") else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dlc_multi: two individuals, the first is taken
        kp = read_tracking(SAMPLES / name)
    assert kp.names == (NAMES if not name.startswith("worm") else ("p0", "p1", "p2"))
    assert kp.points.shape == (F, K, 2)
    np.testing.assert_array_equal(kp.frames, np.arange(F))
    expected = PTS.copy()
    if not name.startswith("dlc"):  # DeepLabCut keeps a position and lowers the likelihood
        expected[2, 2] = np.nan
    np.testing.assert_allclose(kp.points, expected, rtol=0, atol=1e-12)
    if name.startswith("dlc"):
        assert kp.scores[2, 2] == pytest.approx(0.1) and kp.scores[0, 0] == pytest.approx(0.9)
    if name == "worm.wcon":
        assert kp.head == "first"
        np.testing.assert_allclose(kp.times, np.arange(F) / 25)


def test_multi_animal_files_pick_the_named_animal():
    kp = read_tracking(SAMPLES / "dlc_multi.csv", track="fish2")
    np.testing.assert_allclose(kp.points, PTS + 100)
    with pytest.warns(UserWarning, match="fish2"):
        read_tracking(SAMPLES / "dlc_multi.csv")
    with pytest.raises(TrackingFormatError, match="fish3"):
        read_tracking(SAMPLES / "dlc_multi.csv", track="fish3")


def test_layout_variants(tmp_path):
    h5py = pytest.importorskip("h5py")
    # sleap-io's "standard" preset: frame-first arrays, named by a dims attribute
    with h5py.File(tmp_path / "std.h5", "w") as h:
        h["tracks"] = PTS[:, None]  # (frame, track, node, xy)
        h["tracks"].attrs["dims"] = json.dumps(["frame", "track", "node", "xy"])
        h["node_names"] = np.array([n.encode() for n in NAMES])
    np.testing.assert_allclose(read_tracking(tmp_path / "std.h5").points, PTS)
    # WCON: one record per time, centroid origin, zipped, midlines of different lengths
    data = [{"id": 5, "t": i * 40, "x": list(PTS[i, :, 0] - 1), "y": list(PTS[i, :, 1] + 2),
             "cx": 1.0, "cy": -2.0} for i in range(F)]
    data[3]["x"], data[3]["y"] = [10.0, 19.0], [26.0, 24.0]  # a two-point midline
    doc = {"units": {"t": "ms", "x": "mm", "y": "mm", "cx": "mm", "cy": "mm"}, "data": data}
    import zipfile

    with zipfile.ZipFile(tmp_path / "w.wcon.zip", "w") as z:
        z.writestr("w.wcon", json.dumps(doc))
    kp = read_tracking(tmp_path / "w.wcon.zip")
    np.testing.assert_allclose(kp.times, np.arange(F) * 0.04)
    np.testing.assert_allclose(kp.points[[0, 1, 2, 4]], PTS[[0, 1, 2, 4]])
    np.testing.assert_allclose(kp.points[3], [[11.0, 24.0], [15.5, 23.0], [20.0, 22.0]])
    # plain points without a header: x, y pairs
    (tmp_path / "p.csv").write_text("\n".join(",".join(str(v) for v in PTS[i].ravel())
                                              for i in range(F)))
    np.testing.assert_allclose(read_tracking(tmp_path / "p.csv").points, PTS)


def test_hdf5_without_h5py_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(ImportError, match=r"torchconn\[tracking\]"):
        read_tracking(SAMPLES / "sleap.analysis.h5")


# ============================================================================ converter
@pytest.mark.parametrize("n", [3, 5, 9])
@pytest.mark.parametrize("y_down", [True, False])
def test_rendered_keypoints_convert_back_to_the_simulated_trajectory(sims, n, y_down):
    traj, sw = sims[n], NLinkSwimmer(n)
    ppl, noise, origin = 300.0, 0.3, (640.0, 360.0)
    exact = render_keypoints(traj, sw, per_link=1, pixels_per_length=ppl, y_down=y_down,
                             origin_px=origin)[0]
    settings = ConversionSettings(n_links=n, curve="polyline", flip_y=y_down, fps=1 / traj.dt,
                                  scale=ppl)
    out = convert(exact, settings).trajectory
    sign = 1.0 if y_down else -1.0
    shift = torch.tensor([-origin[0] / ppl, sign * origin[1] / ppl], dtype=torch.float64)
    # noise-free: the inverse of the forward kinematics, to rounding
    torch.testing.assert_close(out.r[0], traj.r[0], rtol=0, atol=1e-9)
    torch.testing.assert_close(out.pose[0, :, :2] + shift, traj.pose[0, :, :2], rtol=0, atol=1e-9)
    dth = torch.remainder(out.pose[0, :, 2] - traj.pose[0, :, 2] + math.pi, 2 * math.pi) - math.pi
    assert dth.abs().max() < 1e-9
    # pixel noise: errors at the size the noise predicts (a joint angle between two links of
    # L pixels whose ends move by σ: about 2σ/L rad)
    noisy = render_keypoints(traj, sw, per_link=1, pixels_per_length=ppl, y_down=y_down,
                             origin_px=origin, noise_px=noise, seed=3)[0]
    out = convert(noisy, settings).trajectory
    link_px = ppl / n
    rms_r = float((out.r[0] - traj.r[0]).pow(2).mean().sqrt())
    assert rms_r < 2.0 * (2 * noise / link_px), rms_r
    rms_xy = float((out.pose[0, :, :2] + shift - traj.pose[0, :, :2]).pow(2).mean().sqrt())
    assert rms_xy < 2.0 * noise / ppl, rms_xy
    # the default spline and the median body length recover the same trajectory on a chain
    # drawn with several keypoints per link, to a small bias at the joints' corners
    many = render_keypoints(traj, sw, per_link=4, pixels_per_length=ppl, y_down=y_down)[0]
    spl = convert(many, ConversionSettings(n_links=n, flip_y=y_down, fps=1 / traj.dt))
    assert abs(spl.report.scale / ppl - 1) < 0.02
    assert float((spl.trajectory.r[0] - traj.r[0]).abs().mean()) < 0.1


def test_even_links_need_the_com_mean_frame(sims):
    with pytest.raises(ValueError, match="com-mean"):
        ConversionSettings(n_links=4)
    traj = simulate(NLinkSwimmer(4, frame="com-mean"), _wave(3), eta=0.0, n_cycles=1,
                    seeds=np.array([0]))
    kp = render_keypoints(traj, NLinkSwimmer(4, frame="com-mean"), pixels_per_length=100.0,
                          origin_px=(0.0, 0.0))[0]
    out = convert(kp, ConversionSettings(n_links=4, frame="com-mean", curve="polyline",
                                         fps=1 / traj.dt, scale=100.0, flip_y=True)).trajectory
    torch.testing.assert_close(out.pose[0], traj.pose[0], rtol=0, atol=1e-9)


def test_gaps_blank_or_split(sims):
    traj = sims[3]
    kp = render_keypoints(traj, NLinkSwimmer(3), origin_px=(0.0, 0.0))[0]
    pts = kp.points.copy()
    pts[100:130] = np.nan  # a 30-frame gap
    pts[200, 1] = np.nan  # one lost keypoint
    kp = type(kp)(points=pts, names=kp.names, frames=kp.frames, scores=kp.scores,
                  times=kp.times, source="gappy", format="points")
    base = dict(n_links=3, curve="polyline", flip_y=True)
    blank = convert(kp, ConversionSettings(**base))
    assert blank.trajectory.batch_shape == (1,)
    assert torch.isnan(blank.trajectory.r[0, 100:130]).all()
    assert torch.isnan(blank.trajectory.r[0, 200]).all()
    assert torch.isfinite(blank.trajectory.r[0, 130:200]).all()
    assert blank.report.gaps == ((100, 30), (200, 1))
    dt = traj.dt
    split = convert(kp, ConversionSettings(**base, max_gap=10 * dt))
    assert split.trajectory.batch_shape == (2,)
    assert [t["first_frame"] for t in split.report.trials] == [0, 130]
    assert [t["n_samples"] for t in split.report.trials] == [100, traj.n_samples - 130]
    torch.testing.assert_close(split.trial_times[1][0], traj.t[130])
    # the single-frame gap stays a missing sample inside the second trial
    assert torch.isnan(split.trajectory.r[1, 70]).all()
    torch.testing.assert_close(split.trajectory.r[1, :69], blank.trajectory.r[0, 130:199])


def test_scrambled_keypoint_order_is_reported(sims):
    kp = render_keypoints(sims[3], NLinkSwimmer(3), per_link=2, origin_px=(0.0, 0.0))[0]
    order = [0, 3, 1, 6, 2, 5, 4]  # e.g. node columns sorted by name
    shuffled = type(kp)(points=kp.points[:, order], names=tuple(kp.names[i] for i in order),
                        frames=kp.frames, times=kp.times, source="sorted.csv", format="points")
    with pytest.warns(UserWarning, match="zig-zag"):
        convert(shuffled, ConversionSettings(n_links=3))
    fixed = ConversionSettings(n_links=3, keypoints=kp.names)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # in the right order: no warning
        convert(shuffled, fixed)


def test_flipped_heads_are_found_and_undone(sims):
    traj = sims[3]
    kp = render_keypoints(traj, NLinkSwimmer(3), origin_px=(0.0, 0.0), noise_px=0.2)[0]
    pts = kp.points.copy()
    pts[50:60] = pts[50:60, ::-1]  # the tracker swaps the ends for 10 frames
    swapped = type(kp)(points=pts, names=kp.names, frames=kp.frames, scores=kp.scores,
                       times=kp.times, source="swapped", format="points")
    with pytest.warns(UserWarning, match="head and tail swapped in 10 frame"):
        conv = convert(swapped, ConversionSettings(n_links=3, curve="polyline", flip_y=True))
    assert conv.report.flipped_frames == tuple(range(50, 60))
    ref = convert(kp, ConversionSettings(n_links=3, curve="polyline", flip_y=True))
    torch.testing.assert_close(conv.trajectory.r, ref.trajectory.r)
    # an animal that turned around during a long gap is not a swap
    turned = kp.points.copy()
    turned[100:140] = np.nan
    centre = np.nanmean(turned[140:], axis=1, keepdims=True)
    turned[140:] = 2 * centre - turned[140:]  # rotated by 180 degrees about its centre
    turned = type(kp)(points=turned, names=kp.names, frames=kp.frames, times=kp.times,
                      source="turned", format="points")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        conv = convert(turned, ConversionSettings(n_links=3, curve="polyline", flip_y=True))
    assert conv.report.flipped_frames == ()
    # a whole recording read with the wrong end as head moves tail first
    with pytest.warns(UserWarning, match="tail first"):
        back = convert(kp, ConversionSettings(n_links=3, curve="polyline", flip_y=True,
                                              head="last"))
    assert back.report.tail_first and not ref.report.tail_first


# ============================================================================ commands
def _write_npz(kp, path):
    np.savez(path, points=kp.points, scores=kp.scores, t=kp.times, names=np.array(kp.names))
    return path


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    seeds = np.array([3, 4])
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=8,
                    seeds=seeds)
    kps = render_keypoints(traj, NLinkSwimmer(3), per_link=3, noise_px=0.3, dropout=0.01,
                           seed=5)
    d = tmp_path_factory.mktemp("tracks")
    return [_write_npz(kp, d / f"fish{i}.npz") for i, kp in enumerate(kps)]


def test_fit_from_tracks_equals_fit_from_converted_csvs(tracked, tmp_path):
    opts = ["--links", "3", "--flip-y", "--curve", "polyline"]  # markers on a link chain
    assert convert_main([str(p) for p in tracked] + opts + ["--out", str(tmp_path / "csv")]) == 0
    sidecar = json.loads((tmp_path / "csv" / "convert.json").read_text())
    assert sidecar["settings"]["flip_y"] is True
    assert [f["report"]["keypoints"][0] for f in sidecar["files"]] == ["head", "head"]
    assert set(sidecar["preflight"]["rules"]) == set(CYCLE_RULES)
    csvs = sorted((tmp_path / "csv").glob("*.csv"))
    assert [c.name for c in csvs] == ["fish0.csv", "fish1.csv"]
    args = ["--links", "3", "--no-figures", "--set", "estimator.regression.n_bins=24",
            "--set", "estimator.regression.fourier_order=6"]
    assert fit_main([str(c) for c in csvs] + args + ["--out", str(tmp_path / "a")]) == 0
    assert fit_main([str(p) for p in tracked] + args + opts[2:] + ["--out",
                                                                    str(tmp_path / "b")]) == 0
    a = np.loadtxt(tmp_path / "a" / "connection.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp_path / "b" / "connection.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    side = json.loads((tmp_path / "b" / "fit.json").read_text())
    assert side["settings"]["estimator"]["regression"]["n_bins"] == 24
    assert side["settings"]["estimator"]["pool"] is True
    assert side["data"]["n_trials"] == 2 and len(side["data"]["conversion"]) == 2
    assert "torch" in side["versions"]


@pytest.mark.parametrize("case, args, expect", [
    ("unknown format", ["{d}/fish.xyz", "--links", "3"], ["fish.xyz", "unknown tracking file"]),
    ("missing keypoint", ["{s}/dlc.csv", "--links", "3", "--fps", "25", "--keypoints",
                          "snout,fin,tail"], ["dlc.csv", "'fin'", "snout"]),
    ("one keypoint", ["{d}/one.csv", "--links", "3", "--fps", "25"], ["one.csv", "1 keypoint"]),
    ("frame rate 0", ["{s}/dlc.csv", "--links", "3", "--fps", "0"], ["fps", "positive"]),
    ("below threshold", ["{s}/dlc.csv", "--links", "3", "--fps", "25", "--min-score", "0.95"],
     ["dlc.csv", "0.95", "snout"]),
    ("no time base", ["{s}/dlc.csv", "--links", "3"], ["dlc.csv", "--fps"]),
])
def test_bad_input_gives_a_clear_error_and_exit_code_2(case, args, expect, tmp_path, capsys):
    (tmp_path / "fish.xyz").write_text("1,2\n")
    (tmp_path / "one.csv").write_text("nose_x,nose_y\n1,2\n2,3\n3,4\n")
    args = [a.format(d=tmp_path, s=SAMPLES) for a in args] + ["--out", str(tmp_path / "out")]
    assert convert_main(args) == 2, case
    err = capsys.readouterr().err
    for e in expect:
        assert e in err, (case, err)
    assert not list((tmp_path / "out").glob("*")) if (tmp_path / "out").exists() else True


def test_command_line_errors_have_no_traceback(tmp_path):
    (tmp_path / "fish.xyz").write_text("1,2\n")
    proc = subprocess.run([sys.executable, "-m", "torchconn.convert", str(tmp_path / "fish.xyz"),
                           "--links", "3", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, cwd=Path(__file__).parents[2])
    assert proc.returncode == 2
    assert "fish.xyz" in proc.stderr and "Traceback" not in proc.stderr


# ============================================================================ preflight
def test_preflight_states_one_cycle_rule_per_command_and_warns_on_coarse_sampling():
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=5,
                    samples_per_cycle=8, seeds=np.array([1, 2]))
    pf = preflight(traj)
    assert pf.ready == {"fit": True, "discrepancy": True}
    assert any("8 samples per gait cycle" in w for w in pf.warnings)
    for per_cycle, warned in ((12, True), (16, False)):  # the threshold, 16, and the rate named
        at = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=5,
                      samples_per_cycle=per_cycle, seeds=np.array([1]))
        found = [w for w in preflight(at).warnings if "samples per gait cycle" in w]
        assert bool(found) == warned, (per_cycle, found)
        assert not found or f"only {per_cycle} samples per gait cycle (fewer than 16)" in found[0]
    text = "\n".join(pf.lines())
    assert "fit needs 3 cycles" in text and "discrepancy needs 3 cycles per trial and 10" in text
    short = preflight(traj[:1])  # 5 cycles: enough to fit, not for the discrepancy workflow
    assert short.ready == {"fit": True, "discrepancy": False}
    # a command's rule replaced (the fit's from the phase estimator's min_cycles): measured
    # and printed against it; an unknown command is refused by name
    strict = preflight(traj[:1], rules={"fit": CycleRule(per_trial=6.0, total=6.0)})
    assert strict.ready == {"fit": False, "discrepancy": False}
    assert "hold fewer than 6 cycles" in strict.problems["fit"][0]
    assert "fit needs 6 cycles per trial and 6 in all: NOT ENOUGH" in strict.lines("fit")
    assert strict.to_dict()["rules"]["fit"] == {"per_trial": 6.0, "total": 6.0}
    with pytest.raises(ValueError, match="unknown command.*'fitt'"):
        preflight(traj[:1], rules={"fitt": CycleRule(per_trial=2.0, total=2.0)})
    # a third of the samples lost is still a periodic gait
    lossy = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=6,
                     seeds=np.array([3]))
    lossy = observe(lossy, 0.0, dropout=0.33, seeds=np.array([3]))
    assert preflight(lossy).periodicity[0] > 0.9
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(1, 600, 2, generator=g, dtype=torch.float64)
    flat = Trajectory(t=torch.arange(600, dtype=torch.float64), r=noise,
                      pose=torch.zeros(1, 600, 3, dtype=torch.float64))
    bad = preflight(flat)
    assert not bad.ready["fit"] and "no periodic gait" in bad.problems["fit"][0]


def test_discrepancy_with_the_known_flow_finds_nothing_else(tmp_path, capsys):
    from torchconn.discrepancy import simulate_with_effects
    from torchconn.discrepancy.__main__ import main as discrepancy_main
    from torchconn.io.trajectory_files import write_csv

    flow = {"ambient_flow": {"u_x": -0.01, "u_y": 0.008}}
    traj = simulate_with_effects(NLinkSwimmer(3), reference_gait("3link"), flow, eta=0.025,
                                 n_cycles=12, seeds=[7, 8], omega=0.002)
    path = write_csv(traj, tmp_path / "tank.csv")
    args = [str(path), "--links", "3", "--no-terms", "--no-figures", "--quiet"]
    assert discrepancy_main(args + ["--out", str(tmp_path / "a")]) == 0
    assert "ambient_flow" in capsys.readouterr().out  # unknown, the flow is found
    assert discrepancy_main(args + ["--known", "ambient_flow:u_x=-0.01,u_y=0.008",
                                    "--out", str(tmp_path / "b")]) == 0
    assert "verdict: none" in capsys.readouterr().out  # known, nothing is left


def test_known_ambient_flow_gives_the_recording_relative_to_the_water():
    sw = NLinkSwimmer(3)
    traj = simulate(sw, reference_gait("3link"), eta=0.025, n_cycles=2, seeds=np.array([0]))
    u = torch.tensor([0.01, -0.004], dtype=torch.float64)
    t = traj.t - traj.t[0]
    drifted = traj.with_fields(pose=traj.pose + torch.cat([u * t[:, None],
                                                            torch.zeros_like(t)[:, None]], -1))
    known = parse_known("ambient_flow:u_x=0.01,u_y=-0.004", sw)
    back = relative_to_known(drifted, [known], sw)
    torch.testing.assert_close(back.pose, traj.pose, rtol=0, atol=1e-12)
    torch.testing.assert_close(back.r, traj.r)
    with pytest.raises(ValueError, match="u_x, u_y"):
        parse_known("ambient_flow:speed=1", sw)
