# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 05 — From tracked video to a fitted model
#
# What a locomotion lab has after filming and tracking (SLEAP, DeepLabCut, Tierpsy, its own
# centerline code) is **keypoints per frame, in pixels**, with gaps and confidence scores. This
# notebook goes from there to a model and checks it on a trial it was not fitted to:
#
# 1. raw keypoints: a SLEAP analysis CSV (here rendered from the simulated 3-link swimmer —
#    keypoints along the body, pixel noise, lost points, image y axis pointing down — so the
#    answers can be checked; replace the files with yours);
# 2. `torchconn-convert`: a curve through the keypoints, resampled to an N-link chain, joint
#    angles, body frame, pixels to body lengths; the checks before fitting;
# 3. `torchconn-fit` on the converted trials: phase, limit cycle, connection model;
# 4. a held-out trial: the model's body-velocity prediction against two baselines (the
#    phase-averaged velocity of the training trials, and standing still);
# 5. a flow-tank recording: the same swimmer in a current, modelled relative to the water with
#    `--known ambient_flow:u_x=…,u_y=…`.
#
# No public tracking data set with a licence that allows shipping a sample was found for this
# notebook, so the keypoints are rendered from the simulator.

# %%
import json
import shutil

from _notebook import Notebook  # before pyplot: outside Jupyter it selects the Agg backend

# isort: split
import matplotlib.pyplot as plt
import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, read_csv
from torchconn.convert import main as convert
from torchconn.discrepancy import simulate_with_effects
from torchconn.fit import main as fit
from torchconn.io.tracking import read_tracking
from torchconn.physics.gaits import reference_gait
from torchconn.regression.model import LocalConnectionModel
from torchconn.testing.tracking import render_keypoints, write_sleap_csv
from torchconn.trajectory import pad_trials

torch.set_num_threads(1)
nb = Notebook("05_tracked_video")
N_CYCLES = 8 if nb.small else 25
N_TRIALS = 3  # two to fit, one held out
FPS = 64 / (2 * np.pi)  # 64 frames per gait cycle (a cycle lasts 2π time units)

# %% [markdown]
# ## 1. Keypoints from a video tracker
#
# Ten keypoints from snout to tail tip, 250 pixels per body length, 0.5 px tracking noise,
# 3 % of the points lost (SLEAP leaves them empty), y axis pointing down as in every image.

# %%
swimmer = NLinkSwimmer(3)
seeds = np.arange(N_TRIALS) + 11
truth = simulate_with_effects(swimmer, reference_gait("3link"), {}, eta=0.025,
                              n_cycles=N_CYCLES, seeds=seeds, omega=0.0)
keypoints = render_keypoints(truth, swimmer, per_link=3, pixels_per_length=250.0,
                             noise_px=0.5, dropout=0.03, seed=1)
files = [write_sleap_csv(kp, nb.out / f"fish{i}.analysis.csv") for i, kp in enumerate(keypoints)]
raw = read_tracking(files[0])
print(f"{files[0].name}: {raw.n_frames} frames, keypoints {', '.join(raw.names)}")
print(open(files[0]).read().splitlines()[0][:120], "...")

fig, ax = plt.subplots(figsize=(7, 4))
for f in range(0, 64, 4):
    pts = raw.points[f]
    ax.plot(pts[:, 0], pts[:, 1], "-", color=plt.cm.viridis(f / 64), lw=1)
    ax.plot(pts[0, 0], pts[0, 1], "o", color=plt.cm.viridis(f / 64), ms=3)
ax.invert_yaxis()
ax.set_aspect("equal")
ax.set_xlabel("x (pixels)")
ax.set_ylabel("y (pixels, pointing down)")
ax.set_title("one gait cycle of tracked keypoints (dot: snout)")
nb.save(fig, "raw_keypoints")

# %% [markdown]
# ## 2. Convert
#
# `torchconn-convert fish*.analysis.csv --links 3 --fps F --out DIR` (here called from Python).
# SLEAP and DeepLabCut pixels get their y axis flipped by default; the scale is the median
# chain length; `convert.json` records every assumption and what was found.

# %%
conv_dir = nb.out / "converted"
code = convert([str(f) for f in files] + ["--links", "3", "--fps", str(FPS), "--out",
                                          str(conv_dir)])
assert code == 0
sidecar = json.loads((conv_dir / "convert.json").read_text())
rep = sidecar["files"][0]["report"]
print("settings as resolved:", {k: rep["settings"][k] for k in ("flip_y", "curve", "frame",
                                                                 "head", "min_score")})
print(f"scale {rep['scale']:.1f} px per body length; body length p10-p90 "
      f"{rep['body_length']['p10']:.3f}-{rep['body_length']['p90']:.3f}; "
      f"{rep['n_frames'] - rep['n_valid']} frames missing")

csvs = sorted(conv_dir.glob("fish*.csv"))
converted = read_csv(csvs, n_joints=2)
# a converted trial runs from its first to its last complete frame, so the trials differ in
# length (read_csv pads the shorter ones with NaN): line the simulation up with each of them
spans = [f["report"]["trials"][0] for f in sidecar["files"]]
sim_r = pad_trials([truth.r[b, s["first_frame"]:s["first_frame"] + s["n_samples"]]
                    for b, s in enumerate(spans)], converted.n_samples)
err = converted.r - sim_r
print(f"joint angles against the simulation: mean error {float(err.nanmean()):.1e} rad, RMS "
      f"{float(err.pow(2).nanmean().sqrt()):.3f} rad (pixel noise, and the spline rounding the "
      "link chain's corners)")

fig, axes = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
T = 128
for i, ax in enumerate(axes):
    ax.plot(converted.t[:T], sim_r[0, :T, i], "k-", lw=2, label="simulated")
    ax.plot(converted.t[:T], converted.r[0, :T, i], "C1.", ms=3, label="converted from keypoints")
    ax.set_ylabel(f"$r_{i + 1}$ (rad)")
axes[0].legend(loc="upper right", fontsize=8)
axes[1].set_xlabel("t")
nb.save(fig, "converted_shapes")

# %% [markdown]
# ## 3. Fit on two trials
#
# `torchconn-fit` takes the converted CSVs (or the tracking files directly, with the same
# options). Every estimator setting is reachable with `--set estimator.<name>=value`. Its first
# figure, `held_out_velocity.png`, is the check within the fitted trials: their last third of
# cycles predicted by the fit to the cycles before it.

# %%
fit_dir = nb.out / "fit"
assert fit([str(c) for c in csvs[:2]] + ["--links", "3", "--out", str(fit_dir)]) == 0
model = LocalConnectionModel.load(fit_dir / "model.npz")
# the command's plots, beside the others
for name in ("held_out_velocity.png", "connection.png", "limit_cycle.png"):
    nb.add(shutil.copy(fit_dir / name, nb.out / f"fit_{name}"))

# %% [markdown]
# ## 4. The held-out trial
#
# The model predicts the body velocity from the held-out trial's shapes and phase; the
# baselines are the training trials' body velocity averaged in phase bins (what a
# gait-locked average predicts) and zero.

# %%
train = read_csv(csvs[:2], n_joints=2)
held = read_csv(csvs[2:], n_joints=2)
est = ConnectionEstimator(pool=True).fit(train)
held_p = est.prepare(held)
xi_hat = est.predict(held)[0]
xi_obs = held_p.smoothed.xi[0]
bins = 32
tr = est.trajectory_
b_tr = (torch.remainder(tr.phase, 2 * np.pi) / (2 * np.pi) * bins).long().clamp(max=bins - 1)
xi_tr = tr.smoothed.xi
means = torch.stack([torch.nanmean(xi_tr[b_tr == m], 0) for m in range(bins)])
b_held = (torch.remainder(held_p.phase[0], 2 * np.pi) / (2 * np.pi) * bins).long().clamp(
    max=bins - 1)
xi_avg = means[b_held]
ok = torch.isfinite(xi_obs).all(-1) & torch.isfinite(xi_hat).all(-1)


def rms(a):
    return (a[ok] - xi_obs[ok]).pow(2).mean(0).sqrt()


table = {"connection model": rms(xi_hat), "phase average": rms(xi_avg),
         "zero": rms(torch.zeros_like(xi_obs))}
print(f"{'held-out RMS error':>22}  {'v_x':>9} {'v_y':>9} {'omega':>9}")
for k, v in table.items():
    print(f"{k:>22}  " + " ".join(f"{float(x):9.5f}" for x in v))

fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True)
T = 200
for i, (ax, lab) in enumerate(zip(axes, ("$v_x$", "$v_y$", r"$\omega$"), strict=True)):
    ax.plot(held.t[:T], xi_obs[:T, i], "k-", lw=2, label="measured (smoothed)")
    ax.plot(held.t[:T], xi_hat[:T, i], "C1-", label="connection model")
    ax.plot(held.t[:T], xi_avg[:T, i], "C2--", label="phase average")
    ax.set_ylabel(lab)
axes[0].legend(fontsize=8, loc="upper right")
axes[-1].set_xlabel("t")
nb.save(fig, "held_out_prediction")

# %% [markdown]
# ## 5. A flow-tank recording
#
# The same swimmer in a uniform current (0.01 body lengths per time unit across the tank):
# recorded in the tank's frame, its path drifts. With the current known, `--known` models the
# recording relative to the water, and the fitted connection matches the still-water one.

# %%
current = {"ambient_flow": {"u_x": 0.0, "u_y": 0.01}}
tank = simulate_with_effects(swimmer, reference_gait("3link"), current, eta=0.025,
                             n_cycles=N_CYCLES, seeds=seeds[:2], omega=0.0)
tank_files = [write_sleap_csv(kp, nb.out / f"tank{i}.analysis.csv") for i, kp in
              enumerate(render_keypoints(tank, swimmer, per_link=3, pixels_per_length=250.0,
                                         noise_px=0.5, dropout=0.03, seed=2))]
opts = ["--links", "3", "--fps", str(FPS), "--no-figures"]
assert fit([str(f) for f in tank_files] + opts + ["--out", str(nb.out / "tank_raw")]) == 0
assert fit([str(f) for f in tank_files] + opts + ["--known", "ambient_flow:u_x=0,u_y=0.01",
                                                  "--out", str(nb.out / "tank_known")]) == 0
# the current adds R(θ)ᵀu to the body velocity: it lands in the regression's mean-velocity
# term c(φ), here the body-frame v_y (the swimmer heads along +x)
fig, ax = plt.subplots(figsize=(7, 3.5))
for name, style, label in (("tank_raw", "C3--", "tank, current ignored"),
                           ("tank_known", "C0-", "tank, --known current"),
                           (None, "k:", "still water (section 3)")):
    m = model if name is None else LocalConnectionModel.load(nb.out / name / "model.npz")
    ax.plot(m.bins.phase, m.bins.c[:, 1], style, label=label)
    print(f"{label:>24}: mean c_y = {float(m.bins.c[:, 1].mean()):+.4f} body lengths / time")
ax.set_xlabel("phase (rad)")
ax.set_ylabel("$c_y$ (body lengths / time)")
ax.legend(fontsize=8)
ax.set_title("mean lateral body velocity term, with and without the known current (0.01)")
nb.save(fig, "flow_tank")

nb.finish()
