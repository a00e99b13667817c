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
# # 03 — Discrepancy: where do the simulator and the measurements disagree, and why?
#
# After fitting a model, a locomotion researcher compares it with a simulator of the animal or
# robot. They rarely agree. This notebook runs `torchconn.discrepancy` on "measured" data in
# which a physical effect is hidden — here an **ambient current** the simulator does not know
# about — and follows the workflow:
#
# 1. **Where the gap is**: the measured body velocity minus the nominal simulator's, driven by
#    the measured shapes and passed through the *same* smoothing as the measurement (so filter
#    bias is never called physics), per component and per phase, with bootstrap bands over
#    cycles.
# 2. **Which effect**: every registered effect (ambient flow, drag ratio, marker offset, joint
#    bias, time lag, link lengths, body drift) is fitted by differentiating the augmented
#    simulator; effects are accepted one at a time by held-out gain over blocks of whole cycles.
# 3. **The gap shrinking**: the held-out gap before and after, beside the noise floor.
#
# The same workflow is a command: `torchconn-discrepancy DATA.csv --links 3 --out DIR`.
# The workflow is never told the answer; we check it at the end.

# %%
from _notebook import Notebook  # before pyplot: outside Jupyter it selects the Agg backend

# isort: split
import matplotlib.pyplot as plt
import numpy as np
import torch

from torchconn import NLinkSwimmer
from torchconn.discrepancy import REGISTRY, diagnose, simulate_with_effects
from torchconn.discrepancy.figures import plot_residual_profiles
from torchconn.physics.gaits import reference_gait

nb = Notebook("03_discrepancy")
torch.set_num_threads(1)  # many small tensor ops: one thread is fastest

# %% [markdown]
# ## The registry of effects
#
# Each effect is a documented, parameterised change to the nominal simulator with physical
# units and an "absent" default; `simulate_with_effects` switches them on in rollouts.

# %%
swimmer = NLinkSwimmer(3)
for name, effect in REGISTRY.items():
    params = ", ".join(f"{p.name} [{p.unit}]" for p in effect.param_specs(swimmer))
    print(f"{name}: {params}\n    {effect.description}")

# %% [markdown]
# ## "Measured" data with a hidden current
#
# Three-link swimmer on its reference gait, the paper's α and η, small motion-capture noise,
# and a uniform current of 0.01 body lengths per time unit along the world's y axis (the
# swimmer itself advances about 0.1 body lengths per 2π time units, i.e. 0.016 per time unit).

# %%
n_cycles = 16 if nb.small else 30
seeds = np.arange(3)
hidden = {"ambient_flow": {"u_x": 0.0, "u_y": 0.01}}
measured = simulate_with_effects(swimmer, reference_gait("3link"), hidden, eta=0.025,
                                 n_cycles=n_cycles, seeds=seeds, omega=0.002)
print(f"{measured.batch_shape[0]} trials, {measured.n_samples} samples each")

fig, ax = plt.subplots(figsize=(5, 4))
for k in range(measured.batch_shape[0]):
    ax.plot(measured.pose[k, :, 0], measured.pose[k, :, 1], lw=0.8)
ax.set_xlabel("x (body lengths)")
ax.set_ylabel("y (body lengths)")
ax.set_title("measured paths: the current pushes the swimmer sideways")
ax.set_aspect("equal", "datalim")
nb.save(fig, "paths")

# %% [markdown]
# ## Diagnosis

# %%
report = diagnose(measured, swimmer, log=print)
print(report.summary())

# %% [markdown]
# The report names the effect with its parameter estimates and confidence intervals, says
# whether any other candidate is confounded with it on this gait, and gives the held-out gap
# before and after adding the effect beside the noise floor (per component, RMS body
# velocity).

# %%
print("verdict:", report.verdict)
for e in report.effects:
    print(e["name"], e["parameters"], "95% CI", e["ci"])
print("gap before  ", report.gap_before)
print("gap after   ", report.gap_after)
print("noise floor ", report.noise_floor)
if report.confounded_with:
    print("confounded:", report.confounded_with)

# %% [markdown]
# ## Residual versus phase, before and after

# %%
nb.save(plot_residual_profiles(report), "residuals_before_after")

fig, ax = plt.subplots(figsize=(6, 3.5))
comps = list(report.gap_before)
x = np.arange(len(comps))
ax.bar(x - 0.25, [report.gap_before[c] for c in comps], 0.25, label="nominal simulator")
ax.bar(x, [report.gap_after[c] for c in comps], 0.25, label="with the named effect(s)")
ax.bar(x + 0.25, [report.noise_floor[c] for c in comps], 0.25, label="noise floor")
ax.set_xticks(x, comps)
ax.set_yscale("log")
ax.set_ylabel("held-out RMS gap")
ax.legend(fontsize=8)
nb.save(fig, "gap")

# %% [markdown]
# ## Checking the answer
#
# The workflow was never told what we hid. Did it name the current, and does the interval
# cover the true value?

# %%
named = {e["name"]: e for e in report.effects}
if "ambient_flow" in named:
    e = named["ambient_flow"]
    for p, true in hidden["ambient_flow"].items():
        lo, hi = e["ci"][p]
        print(f"{p}: estimate {e['parameters'][p]:+.4f}, 95% CI [{lo:+.4f}, {hi:+.4f}], "
              f"true {true:+.4f}, covered: {lo <= true <= hi}")
else:
    print("ambient_flow was not named; verdict", report.verdict)

# %% [markdown]
# ## Saving: the report and the augmented model
#
# `report.save(DIR)` writes `report.json` (verdict, effects with intervals, confounding, gaps,
# noise floor), the augmented model that the rest of torchconn loads
# (`torchconn.discrepancy.load_augmented`), and the figures.

# %%
written = report.save(nb.out / "report")
for kind, path in written.items():
    print(kind, path)

nb.finish()
