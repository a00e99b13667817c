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
# # 04 — Your own data: from a CSV file to a connection and a prediction
#
# This notebook is the recipe for recordings of a real swimmer (robot or animal). It
#
# 1. writes a CSV file in the format torchconn reads — here from a simulation, so that we can
#    check the answers; replace it with your file;
# 2. reads it, estimates the phase (Phaser) and the limit cycle, and fits the connection model
#    with all trials pooled;
# 3. plots the connection with confidence bands and the limit cycle, and writes the fitted
#    connection to `connection.csv`;
# 4. uses the model to **predict the motion of gaits you did not record** — nearby
#    variations of the recorded one — and compares with the simulator.
#
# The same steps are available as a command: `torchconn-fit DATA.csv --links 3 --out DIR`.
#
# **The data format** (`docs/conventions.md` in the repository, "Trajectory file format"): one
# CSV per trial, or several trials in one file with an integer `trial` column; a header row,
# then one row per sample, **uniformly sampled**:
#
# | column | meaning | units |
# |---|---|---|
# | `t` | sample time | time units (any; the phase does not care) |
# | `x`, `y` | position of the body-frame origin in the world | body lengths |
# | `theta` | heading of the body frame | rad, wrapped or unwrapped |
# | `r1 … rd` | joint angles: link $i+1$ minus link $i$, counter-clockwise positive | rad |
# | `power` (optional) | mean dissipated power over $[t_k, t_{k+1})$; last row empty | any consistent unit |
#
# Link 1 is the tail. Missing samples (marker drop-outs) are empty or `nan` cells; other
# columns are ignored with a warning. The model then follows the paper's sign,
# $\xi = A(r)\dot r$ with $\xi = g^{-1}\dot g$ the body velocity in the body frame, and the
# phase is in radians, $2\pi$ per cycle.

# %%
import csv
import math
import time

from _notebook import Notebook  # before pyplot: outside Jupyter it selects the Agg backend

# isort: split
import matplotlib.pyplot as plt
import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, TubeRegression, read_csv, simulate, write_csv
from torchconn.fit import connection_table
from torchconn.physics import se2
from torchconn.physics.gaits import FourierGait, evaluate, reference_gait
from torchconn.regression.model import LocalConnectionModel
from torchconn.regression.plots import plot_connection, plot_limit_cycle, plot_metric
from torchconn.simulation import observe

nb = Notebook("04_your_own_data")

# %% [markdown]
# ## 1. Make a data file
#
# We simulate a three-link swimmer following its reference gait with the paper's noise
# ($\alpha = 0.05$, $\eta = 0.025$), add motion-capture noise ($\omega = 0.002$ body lengths /
# rad) and let 1% of the frames drop out, and write all trials to one CSV with
# `torchconn.io.trajectory_files.write_csv`. The simulator's `power` channel is written too, so the metric can
# be estimated. **To use your own recordings, skip this cell and set `DATA` to your file(s).**

# %%
swimmer = NLinkSwimmer(3)  # the "real" swimmer we pretend not to know
recorded_gait = reference_gait("3link")
N_TRIALS, N_CYCLES = (3, 12) if nb.small else (8, 30)
seeds = np.random.SeedSequence(404).generate_state(N_TRIALS)
sim = simulate(swimmer, recorded_gait, eta=0.025, alpha=0.05, n_cycles=N_CYCLES,
               samples_per_cycle=64, seeds=seeds)
recording = observe(sim, 0.002, dropout=0.01, seeds=seeds)
DATA = write_csv(recording, nb.out / "my_swimmer.csv")
print(f"wrote {DATA} ({DATA.stat().st_size / 1e6:.2f} MB): {N_TRIALS} trials x "
      f"{recording.n_samples} samples")
with DATA.open() as fh:
    for _ in range(6):
        print(fh.readline().rstrip())

# %% [markdown]
# ## 2. Read it
#
# `read_csv` accepts one file or a list of files and returns one `Trajectory` with the trials
# as a batch dimension: `pose (trials, T, 3)`, `r (trials, T, d)`, `power (trials, T)`; shorter
# trials are padded with NaN at the end. Passing `n_joints` (here $d = 2$ for three links)
# makes it check the columns; `min_cycles` makes it reject trials that are too short. Errors
# name the file, line and column at fault.

# %%
data = read_csv(DATA, n_joints=2, min_cycles=3)
print(f"trials {tuple(data.batch_shape)}, T = {data.n_samples}, d = {data.shape_dim}, "
      f"dt = {data.dt:.4f}")
print(f"pose {tuple(data.pose.shape)}, r {tuple(data.r.shape)}, power {tuple(data.power.shape)}")
lost = torch.isnan(data.r).any(-1)
print(f"missing samples per trial: {lost.sum(-1).tolist()}")

fig, axes = plt.subplots(1, 2, figsize=(12, 4))
for j in range(N_TRIALS):
    axes[0].plot(data.pose[j, :, 0], data.pose[j, :, 1], lw=0.8, label=f"trial {j}")
axes[0].set(xlabel="x (body lengths)", ylabel="y (body lengths)", aspect="equal",
            title="recorded body paths")
axes[0].legend(fontsize=7, ncol=2)
show = data.t < 3 * 2 * math.pi
for i in range(data.shape_dim):
    axes[1].plot(data.t[show], data.r[0, show, i], label=f"$r_{i + 1}$")
drops = show & lost[0]
axes[1].plot(data.t[drops], np.zeros(int(drops.sum())), "kx", label="lost frames")
axes[1].set(xlabel="t", ylabel="rad", title="trial 0: joint angles, first cycles")
axes[1].legend(fontsize=8)
nb.save(fig, "raw_data")

# %% [markdown]
# ## 3. Smoothing and phase
#
# `ConnectionEstimator.prepare` smooths every channel with a Kalman (RTS) smoother — which
# also fills the lost frames and gives time derivatives $\dot r$ and $\xi = g^{-1}\dot g$ — and
# estimates the **phase** of every sample with Phaser. The phase is unwrapped, in radians,
# advances by $2\pi$ per cycle, and its zero is a Poincaré section: the moment $r_1$'s
# fundamental crosses its mean upwards. That is the same place on the cycle in every trial,
# which is what allows pooling the trials into one model (`pool=True`).
#
# Because this "recording" is a simulation, we can compare Phaser's phase with the true phase
# of the SDE (up to the constant offset between the two zeros). On real data you cannot; look
# at the middle panel instead: plotted against phase, all cycles of all trials should
# collapse onto one curve.

# %%
est = ConnectionEstimator(regression=TubeRegression(n_bins=48, fourier_order=12), pool=True)
prepared = est.prepare(data)
phase = prepared.phase  # (trials, T)
print(f"phase {tuple(phase.shape)}; cycles per trial: "
      f"{((phase[:, -1] - phase[:, 0]) / (2 * math.pi)).numpy().round(2).tolist()}")

diff = torch.remainder(phase - sim.truth.phase + math.pi, 2 * math.pi) - math.pi
offset = torch.atan2(torch.sin(diff).mean(-1), torch.cos(diff).mean(-1))
phase_err = torch.remainder(diff - offset[:, None] + math.pi, 2 * math.pi) - math.pi
print(f"Phaser vs true phase, after removing each trial's offset: RMS "
      f"{float(phase_err.pow(2).mean().sqrt()):.3f} rad")

fig, axes = plt.subplots(1, 3, figsize=(16, 4))
wrapped = torch.remainder(phase, 2 * math.pi)
axes[0].plot(data.t[show], wrapped[0, show], ".", ms=2)
axes[0].set(xlabel="t", ylabel=r"$\varphi$ mod $2\pi$", title="trial 0: estimated phase")
for j in range(N_TRIALS):
    axes[1].plot(wrapped[j], prepared.smoothed.r[j, :, 0], ".", ms=0.8, alpha=0.5)
axes[1].set(xlabel=r"phase $\varphi$ (rad)", ylabel=r"$r_1$ (smoothed)",
            title="all cycles of all trials against phase")
axes[2].plot(data.t / (2 * math.pi), phase_err.T, lw=0.6)
axes[2].set(xlabel="cycle", ylabel="rad", title="Phaser minus true phase (simulation only)")
nb.save(fig, "phase")

# %% [markdown]
# ## 4. Limit cycle and model
#
# `fit` (on the prepared trajectory, so the smoothing and phase are reused) fits the limit
# cycle $\gamma(\varphi)$ — the mean shape at each phase, as a Fourier series — and then the
# regression in every phase bin. `est.limit_cycle_` and `est.model_` are the fitted objects;
# `model.bins` holds the per-bin estimates and their standard errors.
#
# `torchconn.regression.plots` draws the standard figures: the connection entries along the cycle with
# per-bin 95% intervals, the limit cycle over the data, and the metric. For a real swimmer,
# leave out `truth=`; here we overlay the simulator's values at the same cycle points.

# %%
t0 = time.perf_counter()
est.fit(prepared)
model = est.model_
print(f"fitted in {time.perf_counter() - t0:.2f} s; phase rate {float(model.phase_rate):.4f} "
      "rad per time unit")
print(f"per-bin samples: {int(model.bins.n_samples.min())}..{int(model.bins.n_samples.max())}")


def truth_connection(phi):
    return swimmer.connection(model.gamma_at(phi))


def truth_metric(phi):
    return swimmer.metric(model.gamma_at(phi))


nb.save(plot_connection(model, truth=truth_connection), "connection")
nb.save(plot_limit_cycle(model, prepared.smoothed.r, prepared.phase), "limit_cycle")
nb.save(plot_metric(model, truth=truth_metric, time_unit="time unit"), "metric")

# %% [markdown]
# **A word on the metric.** The metric is estimated from the power channel by a regression on
# the products $\dot\delta_i\dot\delta_j$ of the shape-velocity offsets. Those are small and,
# after smoothing, noisy, so $\hat M$ is far less certain than $\hat A$ from the same data:
# check its intervals (and, with a simulation, the truth) before relying on it. The connection
# needs no power channel at all.

# %% [markdown]
# ## 5. `connection.csv`: the fitted model as a table
#
# `torchconn.fit.connection_table(model, n_points)` evaluates the model on a uniform phase
# grid: columns `phase`, the cycle `r1 … rd`, `A_<k>_<i>` ($A^k_i$, $k\in\{x, y, \theta\}$),
# `dA_<k>_<i>_<j>` ($\partial A^k_i/\partial r_j$) and, with a power channel, `M_<i>_<j>`;
# then each estimate's standard error `<column>_se` (the plots' 95% bands are ±1.96 of it).
# That is a file any other tool can read. `model.save` writes the model itself losslessly
# (`LocalConnectionModel.load` reads it back).

# %%
columns, rows = connection_table(model, n_points=100)
table_path = nb.out / "connection.csv"
with table_path.open("w", newline="") as fh:
    writer = csv.writer(fh)
    writer.writerow(columns)
    writer.writerows(rows)
print(f"wrote {table_path}: {len(rows)} rows x {len(columns)} columns")
print(", ".join(columns))
for row in rows[:3]:
    print(", ".join(f"{v:.4g}" for v in row[:9]), ", ...")

model_path = model.save(nb.out / "model.npz")
reloaded = LocalConnectionModel.load(model_path)
phi_check = torch.linspace(0, 2 * math.pi, 7, dtype=torch.float64)
assert torch.allclose(reloaded.connection(phi_check), model.connection(phi_check))
print(f"saved and reloaded {model_path}")

# %% [markdown]
# ## 6. Predicting gaits you did not record
#
# The model knows $A$ *and* $\partial A/\partial r$ along the cycle, so it predicts the body
# velocity for shapes in a tube around the cycle:
#
# $$\hat\xi = \hat c(\varphi) + \hat b(\varphi)\,\delta + \hat A(\varphi)\,\dot\delta
# + \widehat{\partial A/\partial r}(\varphi)\,(\dot\delta\otimes\delta),\qquad
# \delta = r - \gamma(\varphi),\ \dot\delta = \dot r - \dot\gamma(\varphi).$$
#
# To predict a new gait $r_{new}(\psi)$ (executed at one cycle per $2\pi$ time units, so
# $\dot r = dr_{new}/d\psi$):
#
# 1. **match phases**: the model's phase has its own zero, so find the offset $\varphi_0$ for
#    which the model's cycle $\gamma(\psi + \varphi_0)$ is closest to the new gait;
# 2. evaluate `model.predict(psi + phi0, r_new(psi), r_new'(psi))` over one cycle — shape
#    `(P, 3)` — and integrate $\dot g = g\hat\xi$ on SE(2) (`torchconn.physics.se2.integrate`) to get
#    the net displacement $(x, y, \theta)$ per cycle;
# 3. the same with `model.predict_power` gives the cost $\int\sqrt{P}\,dt$.
#
# We try two kinds of variation of the recorded gait: **scaling** it by $1 \pm$ a few percent,
# and **shifting** its centre along the diagonal $r_1 = r_2$ (bending both joints the same
# way, which makes the swimmer turn). The simulator's exact answer comes from
# `torchconn.physics.gaits.evaluate`. The baseline "cycle only" is what a model of $A$ on the cycle
# alone would say: the recorded gait's displacement, whatever the change.

# %%
N_PHI = 512
psi = torch.arange(N_PHI + 1, dtype=torch.float64) * (2 * math.pi / N_PHI)  # closed cycle


def phase_offset(model, gait, n_offsets: int = 720) -> float:
    """phi0 minimising the mean squared distance between gamma(psi + phi0) and gait(psi)."""
    offsets = torch.arange(n_offsets, dtype=torch.float64) * (2 * math.pi / n_offsets)
    r = gait(psi[:-1])
    dist = (model.gamma_at(psi[:-1] + offsets[:, None]) - r).pow(2).sum((-1, -2))
    return float(offsets[dist.argmin()])


def predict_cycle(model, gait, phi0: float):
    """Predicted displacement (3,) and cost of one cycle of ``gait``."""
    r, r_dot = gait(psi), gait.velocity(psi)  # (P, d); dr/dt at one cycle per 2*pi
    xi = model.predict(psi + phi0, r, r_dot)  # (P, 3)
    displacement = se2.integrate(xi, 2 * math.pi / N_PHI, method="midpoint")[-1]
    root_power = model.predict_power(psi + phi0, r, r_dot).clamp_min(0).sqrt()
    cost = float((root_power[1:] + root_power[:-1]).sum()) * math.pi / N_PHI
    return displacement, cost


def scaled(gait, factor: float) -> FourierGait:
    return FourierGait(gait.coeffs * factor)


def shifted(gait, amount: float) -> FourierGait:
    coeffs = gait.coeffs.clone()
    coeffs[0] += amount  # the constant term: move the whole loop by (amount, amount)
    return FourierGait(coeffs)


def fmt(pose) -> str:
    return "(" + ", ".join(f"{float(v):+.4f}" for v in pose) + ")"


phi0 = phase_offset(model, recorded_gait)
print(f"model phase = gait parameter + {phi0:.3f} rad")
base_disp, base_cost = predict_cycle(model, recorded_gait, phi0)

print(f"{'gait':>18}  {'predicted (x, y, theta)':>27}  {'simulator (x, y, theta)':>27}  "
      f"{'cost pred / sim':>15}")
for label, new_gait in (("recorded", recorded_gait),
                        ("scaled x1.05", scaled(recorded_gait, 1.05)),
                        ("shifted +0.05 rad", shifted(recorded_gait, 0.05))):
    pred, cost = predict_cycle(model, new_gait, phase_offset(model, new_gait))
    truth = evaluate(swimmer, new_gait)
    print(f"{label:>18}  {fmt(pred):>27}  {fmt(truth.displacement):>27}  "
          f"{cost:7.3f} / {float(truth.cost):.3f}")

# %% [markdown]
# Now scan both variations and plot the prediction against the simulator. The grey band marks
# the size of the recorded tube: the standard deviation of the offsets $\delta$ in the data.
# Inside it the model interpolates what it has seen; far outside it extrapolates a
# first-order expansion.

# %%
factors = np.linspace(0.85, 1.15, 7)
shifts = np.linspace(-0.15, 0.15, 7)
scan = {"scale": [], "shift": []}
for f in factors:
    g = scaled(recorded_gait, float(f))
    scan["scale"].append((predict_cycle(model, g, phase_offset(model, g))[0].numpy(),
                          evaluate(swimmer, g).displacement.numpy()))
for s in shifts:
    g = shifted(recorded_gait, float(s))
    scan["shift"].append((predict_cycle(model, g, phase_offset(model, g))[0].numpy(),
                          evaluate(swimmer, g).displacement.numpy()))

delta, _ = model.offsets(prepared.phase, prepared.smoothed.r, prepared.smoothed.r_dot)
tube = float(delta.pow(2).mean().sqrt())  # RMS offset per joint (rad)
gamma_size = float(model.gamma_at(psi[:-1]).pow(2).mean().sqrt())  # RMS joint angle on the cycle
print(f"tube: RMS offset {tube:.3f} rad per joint; cycle RMS amplitude {gamma_size:.3f} rad")

fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
panels = [(axes[0], "scale", factors, 0, "x displacement per cycle (body lengths)",
           "gait scaled by factor", 1 + tube / gamma_size, 1 - tube / gamma_size),
          (axes[1], "shift", shifts, 0, "x displacement per cycle (body lengths)",
           "gait shifted by (s, s) rad", tube, -tube),
          (axes[2], "shift", shifts, 2, r"$\theta$ turned per cycle (rad)",
           "gait shifted by (s, s) rad", tube, -tube)]
for ax, kind, knob, comp, ylabel, xlabel, hi, lo in panels:
    pred = np.array([p[comp] for p, _ in scan[kind]])
    true = np.array([t[comp] for _, t in scan[kind]])
    ax.axvspan(lo, hi, color="0.9", label="recorded tube (±1 sd)")
    ax.plot(knob, true, "k-", lw=2, label="simulator (evaluate)")
    ax.plot(knob, pred, "o--", color="tab:green", label="data-driven prediction")
    ax.axhline(float(base_disp[comp]), color="tab:orange", ls=":", label="cycle only")
    ax.set(xlabel=xlabel, ylabel=ylabel)
axes[0].legend(fontsize=8)
axes[0].set_title("scaling the recorded gait")
axes[1].set_title("shifting it: forward speed")
axes[2].set_title("shifting it: turning")
nb.save(fig, "nearby_gaits")

# %% [markdown]
# **Reading the predictions.** Shifting the gait along $r_1 = r_2$ makes the swimmer turn, at
# a rate proportional to the shift; the model, fitted only to noisy cycles of the straight
# gait, predicts that turning rate and the change in forward speed. Scaling is subtler: the
# recorded gait is *x-extremal*, so scaling it changes the forward displacement only at second
# order (the simulator's curve is flat at factor 1). The model's $\partial A/\partial r$ term
# is bilinear in the offsets ($\dot\delta\otimes\delta$), so it carries part of that
# second-order change: with enough data its curve bends like the simulator's inside the tube,
# while with little data (small-data mode) the estimation error of $\partial A/\partial r$
# tilts it. Far outside the tube every prediction is an extrapolation. Gaits that are not
# extremal change at first order, which is what this model is built to predict.
#
# The cost column uses the estimated metric, so it inherits the metric's larger uncertainty.

# %%
nb.finish()
