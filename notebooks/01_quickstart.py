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
# # 01 — Quick start: a data-driven connection for the three-link swimmer
#
# A swimmer at low Reynolds number moves only while it changes shape. Its body velocity is
# a linear function of its shape velocity,
#
# $$\xi = A(r)\,\dot r,$$
#
# where $r\in\mathbb R^d$ are the joint angles, $\xi = (v_x, v_y, \omega)$ is the body velocity
# in the body frame ($\xi = g^{-1}\dot g$) and $A(r)$, a $3\times d$ matrix for every shape, is
# the **local connection**. The dissipated power is $P = \dot r^\top M(r)\,\dot r$ with the
# **metric** $M(r)$. Knowing $A$ (and its shape derivative $\partial A/\partial r$) around a gait
# tells you how the gait moves the body and how small changes of the gait would change that.
#
# The paper this package implements (Bittner, Hatton & Revzen, *A Data-Driven Approach to
# Connection Modeling*) estimates $A$ and $\partial A/\partial r$ **from recordings alone**:
# poses and joint angles of many noisy cycles of a gait. Nothing about the physics is used.
# This notebook walks through the whole pipeline on the simulated three-link (Purcell) swimmer,
# where we know the truth and can check the estimate against it:
#
# 1. build the swimmer and look at $A(r)$, $M(r)$ and the curvature $DA$ over the shape plane;
# 2. simulate noisy trials of the reference gait (the paper's noise model);
# 3. fit the estimator;
# 4. compare $\hat A$ and $\partial\hat A/\partial r$ with the truth along the gait, with 95%
#    confidence intervals, and predict body velocities.
#
# **Conventions** (`docs/conventions.md` in the repository): total body length 1 (all lengths are in body
# lengths), lateral/longitudinal drag ratio 2, body frame at the middle link, the paper's sign
# $\xi = A(r)\dot r$ (Hatton's GSP writes $\xi = -A_{gsp}\dot r$, so $A = -A_{gsp}$), angles in
# radians, and **phase** $\varphi$ in radians with $2\pi$ per gait cycle; on the limit cycle
# $d\varphi/dt = 1$, so one cycle lasts $2\pi$ time units.
#
# *Small-data mode:* with the environment variable `TORCHCONN_SMALL=1` (as under pytest) the
# notebook uses few trials and cycles and runs in seconds; the numbers are then rougher.
# Figures go to `notebooks/_output/01_quickstart/` (or `$TORCHCONN_NB_OUT/01_quickstart/`).

# %%
import math
import time

from _notebook import Notebook  # before pyplot: outside Jupyter it selects the Agg backend

# isort: split
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.patches import Ellipse
from matplotlib.path import Path as PolygonPath

from torchconn import ConnectionEstimator, NLinkSwimmer, TubeRegression, simulate
from torchconn.evaluation.models import clean_trajectory, error_summary, reference_models
from torchconn.physics.gaits import evaluate, reference_gait
from torchconn.simulation import observe

nb = Notebook("01_quickstart")

# %% [markdown]
# ## 1. The swimmer
#
# `NLinkSwimmer(3)` is the viscous three-link swimmer: three equal links of length 1/3, two
# joints, so the shape is $r = (r_1, r_2)$ and $d = 2$. Every method takes shapes with any
# leading batch dimensions, `r: (..., d)`, and returns
#
# | method | shape | meaning |
# |---|---|---|
# | `connection(r)` | `(..., 3, d)` | $A(r)$; row $k$ is $(v_x, v_y, \omega)_k$ per unit $\dot r$ |
# | `metric(r)` | `(..., d, d)` | $M(r)$, power $P = \dot r^\top M \dot r$ |
# | `connection_jacobian(r)` | `(..., 3, d, d)` | $\partial A^k_i/\partial r_j$ at `[.., k, i, j]` |
# | `curvature(r)` | `(..., 3, d(d-1)/2)` | $DA = dA + \sum_{i<j}[A_i, A_j]$ |
#
# A first sanity check against the values in the conventions file: for the straight swimmer
# $A = [[0, 0], [-1/18, -1/18], [7/27, -7/27]]$ and $DA_x = -5/243$.

# %%
swimmer = NLinkSwimmer(3)
print(swimmer)
straight = torch.zeros(2, dtype=torch.float64)
print("A(0) =\n", swimmer.connection(straight).numpy().round(6))
print("expected [[0, 0], [-1/18, -1/18], [7/27, -7/27]] =",
      np.round([[0, 0], [-1 / 18, -1 / 18], [7 / 27, -7 / 27]], 6).tolist())
print("DA_x(0) =", float(swimmer.curvature(straight)[0, 0]), " expected", -5 / 243)

# %% [markdown]
# ## 2. The reference gait
#
# A gait is a closed loop in shape space, $r = \gamma(\varphi)$, $\varphi\in[0, 2\pi)$.
# `reference_gait("3link")` is the Tam–Hosoi-form gait that maximises forward ($x$)
# displacement per cycle. `evaluate` integrates $\dot g = g\,A(r)\dot r$ over one cycle
# (4th-order Magnus on SE(2)): the displacement $(x, y, \theta)$ in body lengths and radians,
# the cost $\int\sqrt{\dot r^\top M\dot r}\,dt$ and the efficiency $|(x,y)|/\text{cost}$.

# %%
gait = reference_gait("3link")
metrics = evaluate(swimmer, gait)
print(f"displacement per cycle (x, y, theta): {metrics.displacement.numpy().round(6)}")
print(f"cost per cycle: {float(metrics.cost):.4f}   efficiency: {float(metrics.efficiency):.4f}")

phi = torch.linspace(0, 2 * math.pi, 400, dtype=torch.float64)
gamma_ref = gait(phi)  # (400, 2)

fig, axes = plt.subplots(1, 2, figsize=(10, 4))
axes[0].plot(gamma_ref[:, 0], gamma_ref[:, 1], color="tab:red")
axes[0].plot(*gamma_ref[0], "o", color="tab:red", label=r"$\varphi = 0$")
axes[0].annotate("", xy=tuple(gamma_ref[12].tolist()), xytext=tuple(gamma_ref[0].tolist()),
                 arrowprops=dict(arrowstyle="->", color="tab:red"))
axes[0].set(xlabel=r"$r_1$ (rad)", ylabel=r"$r_2$ (rad)", title="reference gait in the shape plane",
            aspect="equal")
axes[0].legend()
axes[1].plot(phi, gamma_ref[:, 0], label=r"$r_1$")
axes[1].plot(phi, gamma_ref[:, 1], label=r"$r_2$")
axes[1].set(xlabel=r"phase $\varphi$ (rad)", ylabel="joint angle (rad)",
            title="joint angles over one cycle")
axes[1].legend()
nb.save(fig, "gait")

# %% [markdown]
# ## 3. The connection, the metric and the curvature over the shape plane
#
# Evaluate everything on a grid of shapes in one batched call: the grid is `(n, n, 2)`, so
# `A` comes back `(n, n, 3, 2)` and `M` `(n, n, 2, 2)`.

# %%
n_grid = 31 if nb.small else 61
lim = 2.8
axis = torch.linspace(-lim, lim, n_grid, dtype=torch.float64)
R1, R2 = torch.meshgrid(axis, axis, indexing="xy")
grid = torch.stack([R1, R2], -1)  # (n, n, 2)
A_grid, M_grid = swimmer.connection_and_metric(grid)
DA_grid = swimmer.curvature(grid)[..., 0]  # (n, n, 3): the single pair (1, 2)
print("grid", tuple(grid.shape), "A", tuple(A_grid.shape), "M", tuple(M_grid.shape),
      "DA", tuple(DA_grid.shape))

ROWS = ("x", "y", r"\theta")
fig, axes = plt.subplots(3, 2, figsize=(8, 10), sharex=True, sharey=True)
for k in range(3):
    for i in range(2):
        ax = axes[k, i]
        vmax = float(A_grid[..., k, i].abs().max())
        cs = ax.contourf(R1, R2, A_grid[..., k, i], levels=21, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        fig.colorbar(cs, ax=ax, shrink=0.85)
        ax.plot(gamma_ref[:, 0], gamma_ref[:, 1], "k-", lw=1)
        ax.set_title(f"$A_{{{ROWS[k]},{i + 1}}}(r)$")
        ax.set_aspect("equal")
for ax in axes[-1]:
    ax.set_xlabel(r"$r_1$")
for ax in axes[:, 0]:
    ax.set_ylabel(r"$r_2$")
fig.suptitle("connection entries over the shape plane (black: reference gait)")
nb.save(fig, "connection_field")

# %% [markdown]
# **The metric as an ellipse field.** At each shape, the ellipse is the set of shape velocities
# $\dot r$ that dissipate unit power, $\dot r^\top M(r)\,\dot r = 1$ (drawn scaled down to fit).
# Long axes point in the directions that are cheap to move in; the swimmer pays most for
# moving the joints in the same direction when it is straight.

# %%
step = max(1, n_grid // 9)
sub = slice(step // 2, None, step)
pts, mets = grid[sub, sub].reshape(-1, 2), M_grid[sub, sub].reshape(-1, 2, 2)
evals, evecs = torch.linalg.eigh(mets)
semi = evals.rsqrt()  # semi-axes of {v: vᵀ M v = 1}
scale = 0.45 * float(axis[step] - axis[0]) / float(semi.max())
fig, ax = plt.subplots(figsize=(6, 6))
for p, s, v in zip(pts, semi, evecs, strict=True):
    angle = math.degrees(math.atan2(float(v[1, 1]), float(v[0, 1])))
    ax.add_patch(Ellipse(tuple(p.tolist()), 2 * scale * float(s[1]), 2 * scale * float(s[0]),
                         angle=angle, fc="tab:blue", alpha=0.5, ec="k", lw=0.5))
ax.plot(gamma_ref[:, 0], gamma_ref[:, 1], color="tab:red", lw=1.5, label="reference gait")
ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel=r"$r_1$", ylabel=r"$r_2$",
       title=r"metric: unit-power ellipses $\dot r^\top M(r)\dot r = 1$ (scaled)")
ax.legend(loc="upper right")
nb.save(fig, "metric_ellipses")

# %% [markdown]
# **The curvature $DA$.** For a loop in the shape plane, the net displacement is, to leading
# order, the integral of the curvature over the enclosed area (counter-clockwise positive):
# $g_{\text{cycle}} \approx \iint DA\;dr_1\,dr_2$. The best forward gait encircles the large
# sign-definite region of $DA_x$. Below we check the area rule for the reference gait: it
# runs clockwise, so the enclosed integral enters with a minus sign. Note how the x-extremal
# gait runs along the zero contour of $DA_x$ (thin grey line): pushing the loop outwards there
# would add area of the opposite sign. The area rule is only a first-order estimate; for a
# loop this large, and with the body frame fixed to the middle link, it is a rough one.

# %%
fig, axes = plt.subplots(1, 3, figsize=(16, 4.6), layout="constrained")
for k, ax in enumerate(axes):
    vmax = float(DA_grid[..., k].abs().max())
    cs = ax.contourf(R1, R2, DA_grid[..., k], levels=21, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    ax.contour(R1, R2, DA_grid[..., k], levels=[0.0], colors="0.3", linewidths=0.8)
    fig.colorbar(cs, ax=ax, shrink=0.85)
    ax.plot(gamma_ref[:, 0], gamma_ref[:, 1], "k-", lw=2)
    ax.set(title=f"$DA_{{{ROWS[k]}}}$ with the reference gait", xlabel=r"$r_1$",
           ylabel=r"$r_2$", aspect="equal")
nb.save(fig, "curvature")

loop = gamma_ref.numpy()
signed_area = 0.5 * float(np.sum(loop[:-1, 0] * loop[1:, 1] - loop[1:, 0] * loop[:-1, 1]))
inside = PolygonPath(loop).contains_points(grid.reshape(-1, 2).numpy()).reshape(n_grid, n_grid)
cell = float(axis[1] - axis[0]) ** 2
area_rule = math.copysign(1.0, signed_area) * float(DA_grid[..., 0].numpy()[inside].sum()) * cell
print(f"loop orientation: {'counter-clockwise' if signed_area > 0 else 'clockwise'}")
print(f"x displacement: area rule {area_rule:.4f} vs exact {float(metrics.displacement[0]):.4f}")

# %% [markdown]
# ## 4. Noisy trials: what a motion-capture experiment would record
#
# Real swimmers never repeat a gait exactly. The paper models the shape as the reference gait
# plus a noisy offset (Sec. 5.2):
#
# $$d\varphi = dt + \eta\circ dW_\varphi,\qquad d\delta = -\alpha\,\delta\,dt + \eta\circ dW_\delta,
# \qquad r(t) = \gamma_{\text{REF}}(\varphi(t)) + \delta(t),$$
#
# with $\alpha = 0.05$ (pull back to the gait) and $\eta = 0.025$ (noise). This noise is not a
# nuisance: it is what makes the data informative, because it moves the swimmer through a
# *tube* around the gait, and the regression learns how $\xi$ changes across that tube.
# `simulate` integrates this SDE (Stratonovich, Heun) together with the body motion,
# batched over trials: `seeds` has one entry per trial, and each trial's noise depends only on
# its seed. `observe` then adds motion-capture noise $\omega$ (standard deviation, in body
# lengths and radians) to every recorded $x, y, \theta, r_i$.
#
# The result is a `Trajectory`: `t (T,)`, `pose (trials, T, 3)` = $(x, y, \theta)$ of the body
# frame in the world, `r (trials, T, d)`, `power (trials, T)`, and the hidden `truth` (the
# noise-free data and the true phase), which a real experiment would not have.

# %%
ALPHA, ETA, OMEGA = 0.05, 0.025, 0.002
N_TRIALS, N_CYCLES = (3, 10) if nb.small else (10, 30)
seeds = np.random.SeedSequence(2019).generate_state(N_TRIALS)

t0 = time.perf_counter()
clean = simulate(swimmer, gait, eta=ETA, alpha=ALPHA, n_cycles=N_CYCLES, samples_per_cycle=64,
                 seeds=seeds)
traj = observe(clean, OMEGA, seeds=seeds)
print(f"simulated {N_TRIALS} trials x {N_CYCLES} cycles in {time.perf_counter() - t0:.1f} s")
print(f"t {tuple(traj.t.shape)}, dt = {traj.dt:.4f} (64 samples per 2*pi)")
print(f"pose {tuple(traj.pose.shape)}, r {tuple(traj.r.shape)}, power {tuple(traj.power.shape)}")
print(f"stationary spread of the offset, eta / sqrt(2 alpha) = "
      f"{ETA / math.sqrt(2 * ALPHA):.3f} rad")

# %%
fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
ax = axes[0]
ax.plot(traj.r[..., 0].reshape(-1), traj.r[..., 1].reshape(-1), ".", ms=1, color="0.6",
        label="recorded shapes")
ax.plot(gamma_ref[:, 0], gamma_ref[:, 1], color="tab:red", lw=1.5, label=r"$\gamma_{REF}$")
ax.set(xlabel=r"$r_1$", ylabel=r"$r_2$", title="the tube of shapes around the gait", aspect="equal")
ax.legend(loc="upper right", fontsize=8)
ax = axes[1]
for j in range(min(N_TRIALS, 5)):
    ax.plot(traj.pose[j, :, 0], traj.pose[j, :, 1], lw=1, label=f"trial {j}")
ax.set(xlabel="x (body lengths)", ylabel="y (body lengths)", title="body-frame path in the world",
       aspect="equal")
ax.legend(fontsize=8)
ax = axes[2]
show = traj.t < 3 * 2 * math.pi
ax.plot(traj.t[show], traj.r[0, show, 0], label=r"$r_1$ recorded")
ax.plot(traj.t[show], traj.truth.r[0, show, 0], "k--", lw=0.8, label=r"$r_1$ noise-free")
ax.plot(traj.t[show], traj.r[0, show, 1], label=r"$r_2$ recorded")
ax.set(xlabel="t (2π per cycle)", ylabel="rad", title="trial 0, first three cycles")
ax.legend(fontsize=8)
nb.save(fig, "trials")

# %% [markdown]
# ## 5. Fit the estimator
#
# `ConnectionEstimator` runs the paper's Sec. 4 on the recordings:
#
# 1. **smooth** poses and shapes (Kalman/RTS) and take their time derivatives, giving
#    $\dot r$ and the observed body velocity $\xi = g^{-1}\dot g$;
# 2. estimate the **phase** $\varphi$ of every sample (Phaser). Its zero is a Poincaré section
#    fixed by the data ($r_1$'s fundamental crossing its mean upwards), *not* the zero of the
#    gait's own parameter;
# 3. fit the **limit cycle** $\gamma(\varphi)$, the average shape at each phase;
# 4. in each of `n_bins` phase bins, regress $\xi$ on the offsets $\delta = r - \gamma$,
#    $\dot\delta = \dot r - \dot\gamma$: $\;\xi \approx c + b\,\delta + A\,\dot\delta +
#    \partial A/\partial r\,(\dot\delta\otimes\delta)$, which yields $A(\gamma_m)$ and
#    $\partial A/\partial r(\gamma_m)$ with standard errors;
# 5. interpolate the per-bin estimates by Fourier series in phase (`fourier_order`).
#
# Each step is a stage object you can swap or tune: `smoother=RTSSmoother()` (1),
# `phaser=Phaser()` (2), `cycle=SelfConsistentCycle()` (3), `regression=TubeRegression()`
# (4-5, with `n_bins` and `fourier_order`). `pool=True` fits one model to all trials together
# (the phase section makes them comparable); the default fits one model per trial.

# %%
t0 = time.perf_counter()
est = ConnectionEstimator(regression=TubeRegression(n_bins=48, fourier_order=12), pool=True)
est.fit(traj)
model = est.model_
print(f"{est!r} fitted in {time.perf_counter() - t0:.1f} s")
print(f"phase rate {float(model.phase_rate):.4f} rad per time unit (1 by convention); "
      f"window half-width {model.meta['window']:g} bin spacings")
b = model.bins
print(f"per-bin estimates: A {tuple(b.A.shape)}, dA {tuple(b.dA.shape)}, "
      f"samples per bin {int(b.n_samples.min())}..{int(b.n_samples.max())}")

# %% [markdown]
# **The limit cycle the estimator found.** It should lie on the reference gait (the model's
# phase is shifted with respect to the gait's parameter, which does not matter: all
# comparisons below are made at the model's own cycle points $\gamma(\varphi)$).

# %%
phi = torch.linspace(0, 2 * math.pi, 200, dtype=torch.float64)
gamma_hat = model.gamma_at(phi)  # (200, 2)
fig, ax = plt.subplots(figsize=(5, 5))
ax.plot(traj.r[..., 0].reshape(-1), traj.r[..., 1].reshape(-1), ".", ms=1, color="0.75",
        label="samples")
ax.plot(gamma_ref[:, 0], gamma_ref[:, 1], "k--", lw=1, label=r"$\gamma_{REF}$ (truth)")
ax.plot(gamma_hat[:, 0], gamma_hat[:, 1], color="tab:green", lw=2, label=r"fitted $\gamma$")
ax.plot(*model.gamma_at(torch.zeros(1, dtype=torch.float64))[0], "o", color="tab:green",
        label=r"model's $\varphi = 0$")
ax.set(xlabel=r"$r_1$", ylabel=r"$r_2$", aspect="equal", title="limit cycle")
ax.legend(fontsize=8)
nb.save(fig, "limit_cycle")

# %% [markdown]
# ## 6. The estimated connection against the truth
#
# `model.connection(phi)` evaluates the Fourier series $\hat A(\gamma(\varphi))$, shape
# `(P, 3, d)`; `model.bins` holds the per-bin regression estimates and their standard errors
# (`A_se`), which give the 95% intervals $\pm1.96\,\text{se}$. The truth is the simulator's
# $A$ at the same cycle points: `swimmer.connection(model.gamma_at(phi))`.

# %%
Z95 = 1.96
A_hat = model.connection(phi)  # (P, 3, 2)
A_true = swimmer.connection(gamma_hat)
bin_truth_A = swimmer.connection(b.gamma)  # (M, 3, 2) truth at the bin centres
fig, axes = plt.subplots(3, 2, figsize=(10, 8), sharex=True)
for k in range(3):
    for i in range(2):
        ax = axes[k, i]
        ax.fill_between(b.phase, b.A[:, k, i] - Z95 * b.A_se[:, k, i],
                        b.A[:, k, i] + Z95 * b.A_se[:, k, i], color="tab:green", alpha=0.25,
                        lw=0, label="per-bin 95% interval")
        ax.plot(b.phase, b.A[:, k, i], "o", ms=2.5, color="tab:green", label="per-bin estimate")
        ax.plot(phi, A_hat[:, k, i], color="tab:green", lw=1.5, label="Fourier fit")
        ax.plot(phi, A_true[:, k, i], "k--", lw=1.2, label="simulator (truth)")
        ax.set_title(f"$A_{{{ROWS[k]},{i + 1}}}$ along the gait")
axes[0, 0].legend(fontsize=7)
for ax in axes[-1]:
    ax.set_xlabel(r"model phase $\varphi$ (rad)")
nb.save(fig, "connection_vs_truth")

inside_A = ((b.A - bin_truth_A).abs() <= Z95 * b.A_se).double().mean()
rel_A = (A_hat - A_true).norm() / A_true.norm()
print(f"relative error of A-hat along the cycle: {float(rel_A):.3f}")
print(f"fraction of per-bin 95% intervals that contain the truth: {float(inside_A):.2f}")

# %% [markdown]
# **How good are the intervals?** The 95% intervals come from the regression's standard
# errors, so they measure its variance only. Bias — the first-order model fitted across a
# tube of finite width, the smoothing of the data, errors in the phase — is not in them, so
# with plenty of data the truth falls outside the intervals more often than 5% of the time.
# Judge agreement by eye against the size of the bands, and use more data (or a narrower
# `delta_max`) where the bias matters.
#
# **The shape derivative $\partial A/\partial r$** is what the paper adds over earlier
# empirical connection estimates: it predicts how the body velocity changes when the shape
# leaves the gait. It is learned from the offsets alone, so it is noisier than $A$; the
# intervals say how much to trust it at each phase. Panel $(k; i, j)$ is
# $\partial A^k_i / \partial r_j$. In small-data mode (30 cycles in all) the per-bin estimates
# scatter widely around the truth; the full run (300 cycles) pins them down much better.

# %%
dA_hat = model.connection_jacobian(phi)  # (P, 3, 2, 2)
dA_true = swimmer.connection_jacobian(gamma_hat)
fig, axes = plt.subplots(3, 4, figsize=(15, 8), sharex=True)
for k in range(3):
    for col, (i, j) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        ax = axes[k, col]
        est_b, se_b = b.dA[:, k, i, j], b.dA_se[:, k, i, j]
        ax.fill_between(b.phase, est_b - Z95 * se_b, est_b + Z95 * se_b, color="tab:blue",
                        alpha=0.25, lw=0, label="per-bin 95% interval")
        ax.plot(b.phase, est_b, "o", ms=2.5, color="tab:blue", label="per-bin estimate")
        ax.plot(phi, dA_hat[:, k, i, j], color="tab:blue", lw=1.5, label="Fourier fit")
        ax.plot(phi, dA_true[:, k, i, j], "k--", lw=1.2, label="simulator (truth)")
        ax.set_title(rf"$\partial A_{{{ROWS[k]},{i + 1}}}/\partial r_{j + 1}$", fontsize=10)
axes[0, 0].legend(fontsize=7)
for ax in axes[-1]:
    ax.set_xlabel(r"model phase $\varphi$ (rad)")
nb.save(fig, "connection_jacobian_vs_truth")

inside_dA = ((b.dA - swimmer.connection_jacobian(b.gamma)).abs() <= Z95 * b.dA_se).double().mean()
rel_dA = (dA_hat - dA_true).norm() / dA_true.norm()
print(f"relative error of dA/dr-hat along the cycle: {float(rel_dA):.3f}")
print(f"fraction of per-bin 95% intervals that contain the truth: {float(inside_dA):.2f}")

# %% [markdown]
# ## 7. Predicting body velocities
#
# The model predicts the body velocity of every recorded sample from its phase, shape and
# shape velocity. `torchconn.evaluation.models.reference_models` puts it next to the paper's three
# other models (Sec. 5.1): the **ground truth** $A(r)\dot r$ from the simulator, the
# **analytic** first-order Taylor model of the simulator at the same cycle point, and the
# **template** $A(\gamma)\dot\gamma$, which ignores the offsets. Each is `(trials, T, 3)`.
# With observation noise, the ground truth is evaluated on the noise-free shapes
# (`clean_trajectory`).

# %%
preds = reference_models(swimmer, model, est.trajectory_, clean_trajectory(traj))
truth_xi = preds["ground_truth"]
print(f"{'model':>12}  RMS error vs ground truth (v_x, v_y, omega), mean over trials")
for name in ("data_driven", "analytic", "template"):
    rms = error_summary(preds[name], truth_xi).mean(0)
    print(f"{name:>12}  " + "  ".join(f"{float(v):.2e}" for v in rms))

cyc = 2 * math.pi
window = (traj.t >= 4 * cyc) & (traj.t < 7 * cyc) if N_CYCLES >= 7 else traj.t < 3 * cyc
fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
styles = {"ground_truth": dict(color="k", lw=2.2), "data_driven": dict(color="tab:green", lw=1.2),
          "analytic": dict(color="tab:red", lw=1, ls="--"),
          "template": dict(color="tab:orange", lw=1, ls=":")}
tc = traj.t[window] / cyc
for name, st in styles.items():
    axes[0].plot(tc, preds[name][0, window, 0], label=name.replace("_", "-"), **st)
    if name != "ground_truth":
        axes[1].plot(tc, (preds[name] - truth_xi)[0, window, 0], label=name.replace("_", "-"), **st)
axes[1].axhline(0, color="k", lw=0.8)
axes[0].set_ylabel(r"$v_x$ (body lengths / time)")
axes[1].set_ylabel(r"$v_x$ error vs ground truth")
axes[0].legend(ncol=4, fontsize=8)
axes[1].set_xlabel("cycle")
axes[0].set_title("trial 0: forward body velocity of the four models, and their errors")
nb.save(fig, "body_velocity")

err = {name: (preds[name] - truth_xi)[..., 0] for name in ("data_driven", "analytic", "template")}
fig, ax = plt.subplots(figsize=(6, 3.6))
bins_h = np.linspace(-3e-3, 3e-3, 61)
for name, color in (("data_driven", "tab:green"), ("analytic", "tab:red"),
                    ("template", "tab:orange")):
    ax.hist(err[name].reshape(-1).clamp(-3e-3, 3e-3).numpy(), bins=bins_h, histtype="step",
            color=color, lw=1.5, label=name.replace("_", "-"))
ax.set(xlabel=r"$v_x$ error vs ground truth", ylabel="samples",
       title="error distribution, all samples")
ax.legend(fontsize=8)
nb.save(fig, "error_histogram")

# %% [markdown]
# ## What next
#
# * `02_paper_results.py` reproduces the paper's Figs. 3–4 (error against phase, system noise
#   and observation noise) with the sweep runner, and shows how accuracy depends on the number
#   of cycles recorded, the number of phase bins and the Fourier order.
# * `04_your_own_data.py` runs the same pipeline on a CSV file in the format your motion-capture
#   data should have, writes the fitted connection to `connection.csv`, and predicts the
#   displacement of a gait you have not recorded.

# %%
nb.finish()
