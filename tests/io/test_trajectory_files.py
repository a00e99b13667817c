"""CSV and NPZ input/output: round trips, independently written files, clear errors."""

from __future__ import annotations

import csv
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import AffineConnectionSystem, SmoothedState, Trajectory
from torchconn.io.trajectory_files import count_cycles, load_npz, read_csv, save_npz, write_csv
from torchconn.physics.gaits import FourierGait
from torchconn.simulation.observe import observe
from torchconn.simulation.rollout import simulate

EXACT = dict(rtol=0, atol=0, equal_nan=True)


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    gait = FourierGait(torch.tensor([[0.1, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64))
    sim = simulate(AffineConnectionSystem.random(d=2, seed=3), gait, eta=0.05, n_cycles=3,
                   samples_per_cycle=20, substeps=2, seeds=np.arange(6).reshape(2, 3))
    return observe(sim, 0.01, dropout=0.1, seeds=np.arange(6).reshape(2, 3))


def write_rows(path, header, rows):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def good_rows(n=40, d=2, dt=0.1, cycles=4.0, t0=0.0):
    """An independently made trial: ``r`` runs ``cycles`` cycles in ``n`` samples."""
    rows = []
    for k in range(n):
        t = t0 + k * dt
        ph = 2 * math.pi * cycles * k / n
        r = [math.cos(ph + j) for j in range(d)]
        rows.append([repr(t), repr(0.01 * k), repr(-0.002 * k), repr(0.3 * math.sin(ph))]
                    + [repr(v) for v in r])
    return rows


# ---------------------------------------------------------------------------- round trips
def test_csv_round_trip_single_trial(traj, tmp_path):
    one = traj[1, 2]
    path = write_csv(one, tmp_path / "one.csv")
    header = path.read_text().splitlines()[0]
    assert header == "t,x,y,theta,r1,r2,power"
    back = read_csv(path, n_joints=2)
    assert back.batch_shape == (1,)
    torch.testing.assert_close(back.t, one.t, **EXACT)
    torch.testing.assert_close(back.pose[0], one.pose, **EXACT)
    torch.testing.assert_close(back.r[0], one.r, **EXACT)
    torch.testing.assert_close(back.power[0], one.power, **EXACT)
    assert torch.isnan(back.r).any()  # the drop-outs survived as NaN
    # power belongs to [t_k, t_k+1): the last row's cell is empty and reads back as missing
    assert path.read_text().splitlines()[-1].endswith(",")
    assert torch.isnan(back.power[0, -1]) and torch.isfinite(back.power[0, :-1]).any()


def test_csv_round_trip_flattens_batch_into_trials(traj, tmp_path):
    path = write_csv(traj, tmp_path / "all.csv")
    assert path.read_text().splitlines()[0] == "trial,t,x,y,theta,r1,r2,power"
    back = read_csv(path)
    assert back.batch_shape == (6,)
    torch.testing.assert_close(back.pose, traj.pose.reshape(6, -1, 3), **EXACT)
    torch.testing.assert_close(back.r, traj.r.reshape(6, -1, 2), **EXACT)
    torch.testing.assert_close(back.power, traj.power.reshape(6, -1), **EXACT)
    assert [m["trial"] for m in back.meta["trials"]] == list(range(6))


def test_npz_round_trip_is_lossless(traj, tmp_path):
    T = traj.n_samples
    smoothed = SmoothedState(pose=traj.truth.pose, pose_dot=traj.truth.xi, r=traj.truth.r,
                             r_dot=traj.truth.r_dot, xi=traj.truth.xi)
    full = traj.with_fields(phase=traj.truth.phase + 0.5, smoothed=smoothed,
                            meta={**traj.meta, "note": (1, 2), "tensor": torch.ones(2)})
    path = save_npz(full, tmp_path / "traj")
    assert path.suffix == ".npz" and path.exists()
    back = load_npz(path)
    assert back.batch_shape == (2, 3) and back.n_samples == T
    for name in ("t", "pose", "r", "power", "phase"):
        torch.testing.assert_close(getattr(back, name), getattr(full, name), **EXACT)
    for name in ("phase", "pose", "r", "xi", "r_dot", "power", "delta"):
        torch.testing.assert_close(getattr(back.truth, name), getattr(full.truth, name), **EXACT)
    for name in ("pose", "pose_dot", "r", "r_dot", "xi"):
        torch.testing.assert_close(getattr(back.smoothed, name), getattr(full.smoothed, name),
                                   **EXACT)
    assert back.meta["seeds"] == full.meta["seeds"] and back.meta["omega"] == 0.01
    assert back.meta["note"] == [1, 2] and back.meta["tensor"] == [1.0, 1.0]
    # float32 stays float32
    small = load_npz(save_npz(traj[0, 0].to(torch.float32), tmp_path / "f32.npz"))
    assert small.pose.dtype == torch.float32 and small.t.dtype == torch.float64


def test_load_npz_rejects_foreign_files(tmp_path):
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a torchconn trajectory file"):
        load_npz(tmp_path / "other.npz")


# ---------------------------------------------------------------------------- foreign CSVs
def test_read_independently_written_csv(tmp_path):
    rows = good_rows(n=30)
    rows[4][1] = ""  # a missing x
    rows[5][2:] = ["nan", "NaN", "", ""]  # a lost frame, written two ways
    for k, row in enumerate(rows):
        row.append(repr(0.5 + 0.01 * k))
    path = write_rows(tmp_path / "user.csv", [" t", "X", "y ", "Theta", "r1", "r2", "power"], rows)
    tr = read_csv(str(path), n_joints=2)
    assert tr.batch_shape == (1,) and tr.n_samples == 30 and tr.shape_dim == 2
    assert math.isclose(tr.dt, 0.1, rel_tol=1e-12)
    assert torch.isnan(tr.pose[0, 4, 0]) and not torch.isnan(tr.pose[0, 4, 1:]).any()
    assert torch.isnan(tr.pose[0, 5, 1:]).all() and torch.isnan(tr.r[0, 5]).all()
    assert float(tr.r[0, 7, 1]) == float(rows[7][5])
    assert float(tr.power[0, 29]) == 0.5 + 0.01 * 29
    assert tr.pose.dtype == torch.float64


def test_read_multi_trial_file_and_several_files(tmp_path):
    a, b = good_rows(n=30), good_rows(n=24, t0=5.0)
    rows = [["2"] + r for r in a] + [["7"] + r for r in b]
    rows = rows[::2] + rows[1::2]  # interleaved rows: order within a trial is what counts
    rows = sorted(rows, key=lambda r: (int(r[0]), float(r[1])))
    path = write_rows(tmp_path / "multi.csv", ["trial", "t", "x", "y", "theta", "r1", "r2"],
                      rows)
    tr = read_csv(path)
    assert tr.batch_shape == (2,) and tr.n_samples == 30 and tr.power is None
    assert [m["trial"] for m in tr.meta["trials"]] == [2, 7]
    assert [m["n_samples"] for m in tr.meta["trials"]] == [30, 24]
    assert torch.isnan(tr.r[1, 24:]).all() and not torch.isnan(tr.r[1, :24]).any()
    torch.testing.assert_close(tr.r[1, :24, 0], torch.tensor([float(r[4]) for r in b],
                                                              dtype=torch.float64), **EXACT)
    # several files: trials are concatenated in file order
    single = write_rows(tmp_path / "single.csv", ["t", "x", "y", "theta", "r1", "r2"],
                        good_rows(n=12))
    both = read_csv([path, single])
    assert both.batch_shape == (3,) and both.meta["trials"][2]["file"] == str(single)


def test_different_sampling_intervals_are_refused(tmp_path):
    header = ["t", "x", "y", "theta", "r1", "r2"]
    p1 = write_rows(tmp_path / "a.csv", header, good_rows(dt=0.1))
    p2 = write_rows(tmp_path / "b.csv", header, good_rows(dt=0.05))
    with pytest.raises(ValueError, match=r"b\.csv is sampled every 0\.05 .* every 0\.1"):
        read_csv([p1, p2])


# ---------------------------------------------------------------------------- bad files
HEADER = ["t", "x", "y", "theta", "r1", "r2"]


def _bad(rows_fn=None, header=HEADER):
    rows = good_rows()
    if rows_fn is not None:
        rows = rows_fn(rows)
    return header, rows


def _set(rows, k, j, v):
    rows[k][j] = v
    return rows


@pytest.mark.parametrize(
    "header, rows, kwargs, match",
    [
        (*_bad(lambda r: [row[:3] + row[4:] for row in r],
               ["t", "x", "y", "r1", "r2"]), {}, r"bad\.csv: missing required column\(s\) 'theta'"),
        (*_bad(lambda r: [row[:5] for row in r], ["t", "x", "y", "theta", "r2"]), {},
         "missing required column.*'r1'"),
        (*_bad(lambda r: _set(r, 3, 2, "abc")), {},
         r"bad\.csv, line 5, column 'y': non-numeric value 'abc'"),
        (*_bad(lambda r: _set(r, 6, 0, r[4][0])), {}, r"line 8: t must be strictly increasing"),
        (*_bad(lambda r: _set(r, 6, 0, "")), {}, r"line 8: column 't' is empty"),
        (*_bad(lambda r: r[:10] + r[11:]), {}, r"line 12: t is not uniformly sampled"),
        (*_bad(), {"n_joints": 8}, r"bad\.csv: has 2 joint column\(s\) r1\.\.r2, expected "
         r"n_joints=8"),
        (*_bad(lambda r: [row[:5] + [""] for row in r]), {},
         r"column 'r2' has no values \(all empty or NaN\)"),
        (*_bad(lambda r: r[:1]), {}, r"1 sample\(s\); at least 2 are needed"),
        (*_bad(lambda r: _set(r, 2, 3, "inf")), {}, r"line 4, column 'theta': infinite"),
        (*_bad(lambda r: [r[0]] + [r[1][:4]] + r[2:]), {},
         r"line 3: 4 fields, but the header has 6"),
        (*_bad(), {"min_cycles": 10}, r"too few cycles -- found about 4\.\d gait cycle\(s\), 10 "
         r"are needed"),
        (*_bad(lambda r: [["1.5"] + row for row in r], ["trial"] + HEADER), {},
         r"column 'trial': trial ids must be integers, got '1\.5'"),
        (*_bad(lambda r: [], HEADER), {}, r"no data rows"),
    ],
)
def test_bad_files_raise_clear_errors(tmp_path, header, rows, kwargs, match):
    path = write_rows(tmp_path / "bad.csv", header, rows)
    with pytest.raises(ValueError, match=match):
        read_csv(path, **kwargs)


def test_empty_file_and_duplicate_columns(tmp_path):
    (tmp_path / "empty.csv").write_text("\n\n")
    with pytest.raises(ValueError, match=r"empty\.csv: the file is empty"):
        read_csv(tmp_path / "empty.csv")
    path = write_rows(tmp_path / "dup.csv", HEADER + ["x"], [r + ["0"] for r in good_rows()])
    with pytest.raises(ValueError, match="column 'x' appears more than once"):
        read_csv(path)


def test_unknown_columns_warn_and_are_ignored(tmp_path):
    path = write_rows(tmp_path / "extra.csv", HEADER + ["marker_quality"],
                      [r + ["good"] for r in good_rows()])
    with pytest.warns(UserWarning, match=r"extra\.csv: ignoring unknown column\(s\) "
                                         "'marker_quality'"):
        tr = read_csv(path)
    assert tr.shape_dim == 2


def test_enough_cycles_pass(tmp_path):
    path = write_rows(tmp_path / "ok.csv", HEADER, good_rows(n=80, cycles=6.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr = read_csv(path, min_cycles=5)
    assert tr.n_samples == 80


# ---------------------------------------------------------------------------- count_cycles
def test_count_cycles(traj):
    t = torch.arange(200, dtype=torch.float64)
    ph = 2 * math.pi * 7.0 * t / 200
    r = torch.stack([torch.cos(ph), 0.5 * torch.sin(ph), 0.2 * torch.cos(2 * ph)], -1)
    r = r + 0.05 * torch.randn(200, 3, generator=torch.Generator().manual_seed(0),
                               dtype=torch.float64)
    padded = torch.cat([r[:100], torch.full((100, 3), float("nan"), dtype=torch.float64)])
    counts = count_cycles(torch.stack([r, padded]))
    assert counts.shape == (2,)
    assert abs(float(counts[0]) - 7.0) < 0.25 and abs(float(counts[1]) - 3.5) < 0.25
    # simulated data: 3 cycles per trial (with drop-outs and noise)
    assert torch.allclose(count_cycles(traj.r), torch.full((2, 3), 3.0, dtype=torch.float64),
                          atol=0.25)


SPC = 12  # samples per cycle: a video rate


CYCLES = (9, 14, 20)


def test_recordings_of_different_lengths_read_as_one_padded_batch(unequal_recordings):
    traj = read_csv(unequal_recordings)
    lengths = [CYCLES[k] * SPC for k in range(3)]
    assert traj.n_samples == max(lengths)
    assert [t["n_samples"] for t in traj.meta["trials"]] == lengths
    for k, n in enumerate(lengths):  # NaN after each trial's end
        assert torch.isnan(traj.r[k, n:]).all() and torch.isfinite(traj.r[k, n - 3]).any()
