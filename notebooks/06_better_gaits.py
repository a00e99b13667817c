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
# # 06 — Better gaits from data
#
# The paper closes with its most promising extension: use the local, data-driven model to reason
# about gait *improvements*. The fitted model knows `Â`, `∂Â/∂r` (and `M̂` with a power channel) in
# a tube around the recorded gait, so it can predict what a **nearby** gait would do — without a
# simulator and without the equations of motion. `torchconn.improve` turns that into a loop:
#
# **record → fit → propose a better nearby gait → record it → …**
#
# 1. `model.evaluate_gait(gait)`: displacement, cost and efficiency of a nearby gait from the
#    model alone, with standard errors and the gait's distance from the data (in tube radii).
# 2. `propose_gait(model, objective, trust_region)`: the best gait within a trust region sized by
#    the tube the data covered, with the predicted gain and its interval.
# 3. `improve(system, start, settings)`: the loop on a simulator, a few cycles at a time, with one
#    model from every gait recorded (`PooledConnection`), judged by the simulator's exact
#    displacement of every gait (never shown to the loop).
#
# The same loop is a command: `python -m torchconn.improve simulate --links 3 --out DIR`, and
# `python -m torchconn.improve propose round2/*.csv --earlier round1/*.csv --links 3 --out DIR`
# proposes the next gait from your own recordings of every round (joint-angle time series and
# Fourier coefficients).

# %%
from _notebook import Notebook  # before pyplot: outside Jupyter it selects the Agg backend

# isort: split
import warnings

import matplotlib.pyplot as plt
import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression, simulate
from torchconn.improve import (
    LoopSettings,
    TrustRegion,
    ceiling,
    circle_gait,
    exact_local_model,
    improve,
    propose_gait,
    true_objective,
)
from torchconn.improve.plots import plot_gaits, plot_rounds
from torchconn.physics.gaits import FourierGait, evaluate

nb = Notebook("06_better_gaits")
torch.set_num_threads(1)
trials, cycles = (2, 12) if nb.small else (4, 20)
rounds = 3 if nb.small else 10

# %% [markdown]
# ## 1. What the model predicts for a nearby gait
#
# Record a small circle gait of the 3-link swimmer (radius 0.5 rad about the straight shape),
# fit one pooled model (the noise-aware regression, as the loop does: on these small loops its
# `∂Â/∂r` is off by 6-9 %, the default tube regression's by 40-200 %), and ask it about gaits
# that are a little larger. The simulator's exact answer (`gaits.evaluate`) is the reference;
# the exact local model (what a perfect estimator would give) separates the first-order model's
# own truncation error from the estimation error.

# %%
swimmer = NLinkSwimmer(3)
start = circle_gait(2, 0.5)
traj = simulate(swimmer, start, eta=0.025, n_cycles=cycles, seeds=np.arange(trials))
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    model = ConnectionEstimator(pool=True, regression=NoiseAwareRegression()).fit(traj).model_
cycle = FourierGait(model.gamma.coeffs)
exact = exact_local_model(swimmer, cycle, tube_rms=0.08)
print("tube RMS per joint (rad):", [round(v, 3) for v in model.meta["tube_rms"]])

scales = np.linspace(0, 0.5, 6)
pred, lo, hi, true, ex = [], [], [], [], []
for s in scales:
    c = model.gamma.coeffs.clone()
    c[1:3] *= 1 + s / 0.5  # a radius larger by s rad
    gait = FourierGait(c)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = model.evaluate_gait(gait, phase_offset=0.0, max_excursion=100)
        e = exact.evaluate_gait(gait, phase_offset=0.0, n_draws=0, max_excursion=100)
    pred.append(float(p.displacement[0]))
    a, b = p.interval()
    lo.append(float(a[0]))
    hi.append(float(b[0]))
    true.append(float(evaluate(swimmer, gait).displacement[0]))
    ex.append(float(e.displacement[0]))
    print(f"+{s:.1f} rad: {float(p.excursion):4.1f} tube radii, predicted x "
          f"{pred[-1]:.4f} [{lo[-1]:.4f}, {hi[-1]:.4f}], exact local model {ex[-1]:.4f}, "
          f"true {true[-1]:.4f}")

fig, ax = plt.subplots(figsize=(6, 4))
ax.fill_between(scales, lo, hi, alpha=0.3, label="fitted model, 95%")
ax.plot(scales, pred, "o-", label="fitted model")
ax.plot(scales, ex, "s--", label="exact local model (first order)")
ax.plot(scales, true, "k^:", label="simulator (truth)")
ax.set_xlabel("radius added to the recorded gait (rad)")
ax.set_ylabel("x displacement per cycle")
ax.legend()
nb.save(fig, "nearby_gaits")

# %% [markdown]
# ## 2. One proposal
#
# `propose_gait` maximises the predicted |(x, y)| per cycle over changes of the cycle (a Fourier
# series of order 3 per joint) whose largest step is 3 tube radii.

# %%
prop = propose_gait(model, "displacement", TrustRegion(scale=3.0))
a, b = prop.gain_interval()
print(f"model: current {prop.current:.4f}, proposed {prop.predicted:.4f}, gain {prop.gain:.4f} "
      f"[{a:.4f}, {b:.4f}]; step {prop.step:.3f} rad (trust radius {prop.radius:.3f})")
print(f"simulator: current {true_objective(swimmer, cycle, 'displacement'):.4f}, proposed "
      f"{true_objective(swimmer, prop.gait, 'displacement'):.4f}")

# %% [markdown]
# ## 3. The loop, a few cycles at a time
#
# Each step records 3 cycles of one gait, and the model is **one regression over every
# recording so far**, each weighted by its distance from the current gait: earlier gaits are
# data off the current cycle, so the tube (and the trust radius, in tube radii) widens as the
# loop moves. After every recording the loop proposes, and moves to the proposal only when the
# 95 % interval of its gain lies above zero. Otherwise it records the current gait again,
# perturbed along the joints where `∂Â/∂r` is least known (deliberate excitation). The
# predicted value of a proposal is the measured value of its start plus the model's gain,
# less the over-prediction learnt from the steps taken (it grows as the step²). The proposals
# swim straight (at most 0.05 rad of turning per cycle); the ceiling is the ascent with the
# true connection from the same start, in the same family and limits (skipped in small-data
# mode: it takes a minute).

# %%
settings = LoopSettings(rounds=rounds, seed=1)
result = improve(swimmer, start, settings, progress=lambda r: print(
    f"{r.cycles_used:3d} cycles: recorded {r.kind}, observed {r.observed:.4f} ± "
    f"{r.observed_se:.4f}; kept gait's true value {r.kept_true:.4f}; "
    + (f"moving to a proposal predicted {r.predicted:.4f} [{r.predicted_low:.4f}, "
       f"{r.predicted_high:.4f}], realised {r.realised:.4f}" if r.moved else "recording again")))
best_true = None if nb.small else ceiling(swimmer, "displacement", settings, starts=[start],
                                          peaks=(), random_starts=0).value
print(f"ascent with the true connection from the same start: {best_true}; kept gait after "
      f"{result.rounds[-1].cycles_used} cycles: {result.rounds[-1].kept_true:.4f}; "
      f"intervals covered {result.coverage:.0%} of the proposals the loop moved to")
nb.save(plot_gaits(result, swimmer), "loop_gaits")
nb.save(plot_rounds(result, ceiling=best_true), "loop_objective")

# %% [markdown]
# ## 4. More joints
#
# The 9-link swimmer has 8 joints; the proposals move in all of them (plotted on the first two
# principal components of the recorded shapes). In small-data mode this is skipped.

# %%
if not nb.small:
    nine = NLinkSwimmer(9)
    result9 = improve(nine, circle_gait(8, 0.5), LoopSettings(rounds=rounds, seed=1))
    print(f"9-link: start {result9.start_true:.4f} -> kept gait "
          f"{result9.rounds[-1].kept_true:.4f} after {result9.rounds[-1].cycles_used} cycles")
    nb.save(plot_gaits(result9, nine), "loop9_gaits")
    nb.save(plot_rounds(result9), "loop9_objective")

# %%
nb.finish()
