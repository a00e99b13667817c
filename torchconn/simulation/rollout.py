"""Batched stochastic rollouts of a swimmer following a noisy gait (the paper's eq. ``simsde``).

The shape follows the Stratonovich SDE of the paper's Sec. 5.2 (docs/conventions.md,
"Phase and noise")::

    dφ = dt + η∘dW_φ,    dδ = −αδ dt + η∘dW_δ,    r(t) = γ_REF(φ(t)) + δ(t),

with noise on the phase and on every one of the ``d`` joints, and the body moves by the
reconstruction equation ``dg = g A(r)∘dr`` (plus, optionally, an extra body-frame velocity
``drift(g, t) dt``, the hook the discrepancy stage uses for ambient flow or body drift).

Scheme
    Heun's predictor–corrector (the trapezoid rule), which converges to the Stratonovich
    solution, on the fine step ``h = 2π / (samples_per_cycle · substeps)``. The shape process
    does not depend on the pose, so it is advanced first (``φ`` exactly, ``δ`` by Heun -- with
    its linear drift a linear recurrence, evaluated by a parallel scan, not step by step); the
    pose step then takes the trapezoid of the connection at both ends of the shape step,
    ``g_{n+1} = g_n exp(½(A(r_n) + A(r_{n+1})) Δr_n)``, composed on SE(2). ``A`` is evaluated once
    per fine point and shared by the two steps that meet there. A drift is added to the twist
    by Heun as well (predictor pose, averaged drift). Without a Lévy-area term the pose
    converges strongly with order ½ in ``h`` (faster while the deterministic part dominates).

Recording
    Every ``substeps`` fine steps a sample is recorded at ``t_k = k Δt``, ``Δt = 2π /
    samples_per_cycle``, ``k = 0 … n_cycles·samples_per_cycle − 1``: the pose ``(x, y, θ)``
    (θ unwrapped) and ``r``. Each sample owns the recording interval ``[t_k − Δt/2, t_k + Δt/2]``
    centred on it; the path is simulated from ``−Δt/2`` (where ``g = e`` and
    ``φ = phase0 − Δt/2``, so a noise-free run has ``φ(t) = phase0 + t``) to the end of the last
    interval. Per interval (accumulated on the fly; only recorded samples are stored):

    - ``truth.xi``: the mean body velocity, ``Σ_n twist_n / Δt`` over the interval's fine
      steps, ``twist_n = ½(A(r_n) + A(r_{n+1})) Δr_n (+ drift h)``, i.e. ``∫ g⁻¹∘dg / Δt``;
    - ``truth.r_dot``: the mean shape velocity ``(r(t_k + Δt/2) − r(t_k − Δt/2)) / Δt``;
    - ``power``: on the observable sample interval (docs/conventions.md, "Trajectory file format"): row ``k``
      holds the mean dissipated power over ``[t_k, t_{k+1})``, recorded as
      ``v_kᵀ M(r̄_k) v_k`` with ``v_k = (r_{k+1} − r_k)/Δt`` and ``r̄_k = (r_k + r_{k+1})/2`` from
      the recorded (true, noise-free) shapes at the sample times; the last row is NaN (its
      interval ends after the recording). Why not the mean of the fine-path power
      ``(Δr_n/h)ᵀ M (Δr_n/h)``: **the SDE path is rough** (``Δr ~ η √h``), so that mean carries
      a part ``≈ η² tr M / h`` that diverges as the fine step shrinks -- it measures the
      integrator's step, not the swimmer. And why the sample interval, not one centred on the
      sample: a regression sees only the recorded samples, and ``v_k`` is exactly what their
      differences give, so the power is matched from the data (:func:`interval_power`).

Randomness
    ``seeds`` is an integer array of the batch shape. Every cell draws its initial offset and its
    Brownian increments from its own ``torch.Generator`` seeded from ``(seed, "rollout")`` (see
    :func:`cell_generators`), in blocks whose sizes depend only on the time grid, so a cell's
    path does not depend on which other cells share the batch. The time stepping itself is
    batched over all cells. Cells with the same seed but different ``eta`` share their standard
    normal draws (common random numbers across noise levels).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from .. import _checks
from ..phase._scan import scan_states
from ..physics import se2
from ..physics.gaits import as_gait
from ..physics.systems.base import LocomotionSystem
from ..trajectory import GroundTruth, Trajectory

__all__ = ["simulate", "cell_generators", "interval_power", "POWER_DEFINITION", "seed_array", "per_cell",
           "meta_value"]

POWER_DEFINITION = (
    "power at sample k belongs to the sample interval [t_k, t_k+1): v_k^T M(rbar_k) v_k with "
    "v_k = (r_k+1 - r_k)/dt and rbar_k = (r_k + r_k+1)/2 from the true recorded shapes; the last "
    "row is NaN (the mean of the fine-path power would diverge like eta^2 tr M / h on the rough "
    "SDE path)"
)

#: fine steps per noise draw (rounded to whole recording intervals); fixed so that a cell's
#: noise draws, hence its path, do not depend on the batch -- changing it changes every path
_BLOCK_FINE_STEPS = 32
#: fine steps integrated together (whole noise draws): the connection is evaluated on this
#: many fine points of every cell at once (a Fig. 4A cell: 32 -> 256 cut the rollout's CPU time
#: by a third); fixed, not sized to the batch, so that rounding does not depend on the batch
_STEP_FINE_STEPS = 256

_STREAMS = {"rollout": 0, "observe": 1}

Drift = Callable[[Tensor, float], Tensor]


# ---------------------------------------------------------------------------- randomness
def seed_array(seeds, name: str = "seeds") -> np.ndarray:
    """Seeds as an object array of non-negative Python ints (batch shape kept)."""
    if isinstance(seeds, np.random.SeedSequence):
        seeds = [seeds]
        scalar = True
    else:
        scalar = False
    if isinstance(seeds, Tensor):
        seeds = seeds.detach().cpu().numpy()
    arr = np.asarray(seeds, dtype=object) if not isinstance(seeds, np.ndarray) else seeds
    if arr.dtype == object:
        flat = []
        for s in arr.reshape(-1):
            if isinstance(s, np.random.SeedSequence):
                s = int(s.generate_state(1, np.uint64)[0])
            if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)):
                raise TypeError(
                    f"{name} must be an integer array of the batch shape (or SeedSequences), "
                    f"got an element {s!r}"
                )
            flat.append(int(s))
        arr = np.array(flat, dtype=object).reshape(arr.shape)
    elif np.issubdtype(arr.dtype, np.integer):
        arr = np.array([int(s) for s in arr.reshape(-1)], dtype=object).reshape(arr.shape)
    else:
        raise TypeError(
            f"{name} must be an integer array of the batch shape, e.g. "
            f"numpy.random.SeedSequence(root).generate_state(n), got dtype {arr.dtype}"
        )
    if scalar:
        arr = arr.reshape(())
    if any(s < 0 for s in arr.reshape(-1)):
        raise ValueError(f"{name} must be non-negative integers")
    if arr.size == 0:
        raise ValueError(f"{name} is empty; pass one seed per batch cell")
    return arr


def cell_generators(
    seeds, stream: str = "rollout", device: torch.device | str | None = None
) -> tuple[list[torch.Generator], tuple[int, ...]]:
    """One ``torch.Generator`` per batch cell, and the batch shape.

    Args:
        seeds: non-negative integers of the batch shape ``(...)`` (array, tensor, nested list)
            or ``numpy.random.SeedSequence`` objects (e.g. ``SeedSequence(root).spawn(n)``).
        stream: ``"rollout"`` or ``"observe"``; the generator of a cell is seeded from
            ``SeedSequence(seed, spawn_key=(stream_id,))``, so the same seeds passed to
            :func:`simulate` and :func:`torchconn.simulation.observe.observe` give independent noise.
        device: device of the generators.

    Returns:
        ``(generators, batch_shape)`` with the generators in C order of the batch.
    """
    if stream not in _STREAMS:
        raise ValueError(f"stream must be one of {tuple(_STREAMS)}, got {stream!r}")
    arr = seed_array(seeds)
    key = _STREAMS[stream]
    gens = []
    for s in arr.reshape(-1):
        state = np.random.SeedSequence(s, spawn_key=(key,)).generate_state(1, np.uint64)[0]
        gens.append(torch.Generator(device=device).manual_seed(int(state)))
    return gens, tuple(arr.shape)


def per_cell(value, name: str, batch: tuple[int, ...], dtype, device) -> Tensor:
    """A float or a tensor broadcastable to ``batch`` -> flat ``(B,)`` tensor."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    try:
        t = torch.broadcast_to(t, batch)
    except RuntimeError:
        raise ValueError(
            f"{name} must be a float or a tensor broadcastable to the batch shape {batch} "
            f"(the shape of seeds), got shape {tuple(t.shape)}"
        ) from None
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    return t.reshape(-1)


def meta_value(value):
    """``value`` as written to a recording's metadata: a tensor becomes a (nested) list, any
    other value is returned as is."""
    return value.detach().cpu().tolist() if isinstance(value, Tensor) else value


# ---------------------------------------------------------------------------- public entry
def simulate(
    system: LocomotionSystem,
    gait,
    *,
    eta,
    alpha=0.05,
    n_cycles: int = 30,
    samples_per_cycle: int = 64,
    substeps: int = 8,
    seeds,
    phase0=0.0,
    stationary_start: bool = True,
    drift: Drift | None = None,
    power: bool = True,
) -> Trajectory:
    """Simulate noisy gait-following trials, batched over cells (noise levels × trials).

    Args:
        system: a :class:`~torchconn.physics.systems.LocomotionSystem` with ``d`` joints.
        gait: the reference gait ``γ_REF`` (gait object or callable ``φ -> r``), ``d`` joints.
        eta: noise magnitude η ≥ 0, a float or a tensor broadcastable to the batch shape
            (e.g. ``(L, 1)`` for ``L`` noise levels × trials); its floating dtype and device are
            followed (default float64, CPU).
        alpha: attraction rate α of the shape offset (float or broadcastable tensor, ≥ 0;
            > 0 when ``stationary_start``).
        n_cycles: recorded duration in gait periods (2π time units each).
        samples_per_cycle: recorded samples per period; ``Δt = 2π / samples_per_cycle``.
        substeps: fine steps per recorded sample (even, ≥ 2); ``h = Δt / substeps``.
        seeds: non-negative integers of the batch shape ``(...)`` (see :func:`cell_generators`).
        phase0: phase at ``t = 0`` of a noise-free run (float or broadcastable tensor).
        stationary_start: draw ``δ(−Δt/2) ~ N(0, η²/(2α))`` per joint (else ``δ = 0``).
        drift: optional extra body-frame velocity ``drift(pose (..., 3), t) -> (..., 3)``, added
            to ``g⁻¹ġ`` (pose in the world frame, ``t`` a float). A drift with the attribute
            ``heading_only = True`` promises that it reads only the heading ``pose[..., 2]`` and
            ``t``, and that its ω component does not depend on the pose (ambient flow, body
            drift); it is then called once per block, vectorised, with poses ``(..., K, 3)``
            whose ``x, y`` are NaN and ``t`` a ``(K,)`` tensor, which is much faster.
        power: record the power channel (:func:`interval_power`); False leaves ``power`` None,
            for a caller that fits no metric (the same trajectory otherwise, bit for bit).

    Returns:
        A :class:`~torchconn.trajectory.Trajectory` with ``t (T,)``, ``pose (..., T, 3)``,
        ``r (..., T, d)``, ``power (..., T)`` and ``truth`` (phase, noise-free pose / r / power,
        ``xi``, ``r_dot``, ``delta``), ``T = n_cycles · samples_per_cycle``.
    """
    gait = _checked_run(system, gait, n_cycles, samples_per_cycle, substeps, drift)
    d = system.shape_dim
    like = eta if isinstance(eta, Tensor) and eta.is_floating_point() else None
    dtype = like.dtype if like is not None else torch.float64
    device = like.device if like is not None else torch.device("cpu")
    gens, batch = cell_generators(seeds, "rollout", device)
    eta_c, alpha_c, phase0_c = _cell_parameters(eta, alpha, phase0, stationary_start, batch,
                                                dtype, device)

    kw = dict(dtype=dtype, device=device)
    if stationary_start:
        std = eta_c / torch.sqrt(2 * alpha_c)
        delta0 = torch.stack([torch.randn(d, generator=g, **kw) for g in gens]) * std[:, None]
    else:
        delta0 = torch.zeros(len(gens), d, **kw)

    def noise(n_steps: int) -> Tensor:
        return torch.stack([torch.randn(n_steps, d + 1, generator=g, **kw) for g in gens])

    dt = 2 * math.pi / samples_per_cycle
    n_samples = n_cycles * samples_per_cycle
    rec = _integrate(
        system, gait, eta=eta_c, alpha=alpha_c, phase0=phase0_c, delta0=delta0, noise=noise,
        n_samples=n_samples, dt=dt, substeps=substeps, drift=drift, batch=batch,
    )

    t = torch.arange(n_samples, dtype=torch.float64, device=device) * dt
    power = interval_power(system, rec["r"], dt) if power else None
    truth = GroundTruth(
        phase=rec["phase"], pose=rec["pose"], r=rec["r"], xi=rec["xi"], r_dot=rec["r_dot"],
        power=power, delta=rec["delta"],
    )
    meta = _rollout_meta(system, gait, eta=eta, alpha=alpha, phase0=phase0, seeds=seeds,
                         batch=batch, n_cycles=n_cycles, samples_per_cycle=samples_per_cycle,
                         substeps=substeps, dt=dt, stationary_start=stationary_start,
                         drift=drift, power=power is not None)
    return Trajectory(t=t, pose=rec["pose"], r=rec["r"], power=power, truth=truth,
                      meta=meta)


def _rollout_meta(system, gait, *, eta, alpha, phase0, seeds, batch, n_cycles,
                  samples_per_cycle, substeps, dt, stationary_start, drift, power) -> dict:
    """The metadata of a simulated recording: the system, gait and every setting of the run."""
    return {
        "source": "torchconn.simulation.rollout.simulate",
        "system": repr(system),
        "gait": repr(gait),
        "eta": meta_value(eta),
        "alpha": meta_value(alpha),
        "phase0": meta_value(phase0),
        "seeds": seed_array(seeds).tolist(),
        "batch_shape": list(batch),
        "n_cycles": int(n_cycles),
        "samples_per_cycle": int(samples_per_cycle),
        "substeps": int(substeps),
        "dt": dt,
        "h": dt / substeps,
        "t_start": -dt / 2,
        "stationary_start": bool(stationary_start),
        "drift": None if drift is None else repr(drift),
        "scheme": "Heun (Stratonovich), pose step exp(½(A(r_n)+A(r_n+1)) Δr) on SE(2)",
        "power": POWER_DEFINITION if power else None,
    }


def _checked_run(system, gait, n_cycles, samples_per_cycle, substeps, drift):
    """The gait as a gait object, after checking the system, the gait's joints, the integer
    sizes of the run (``substeps`` even) and that ``drift`` is callable."""
    if not isinstance(system, LocomotionSystem):
        raise TypeError(f"system must be a LocomotionSystem, got {type(system).__name__}")
    gait = as_gait(gait)
    d = system.shape_dim
    if gait.shape_dim != d:
        raise ValueError(f"gait has {gait.shape_dim} joints but the system has {d}")
    for name, v, lo in (("n_cycles", n_cycles, 1), ("samples_per_cycle", samples_per_cycle, 2),
                        ("substeps", substeps, 2)):
        _checks.integer(v, name, minimum=lo)
    if substeps % 2:
        raise ValueError(
            f"substeps must be even (each sample sits mid-way through its {substeps} fine "
            "steps' recording interval), got {substeps}"
        )
    if drift is not None and not callable(drift):
        raise TypeError(f"drift must be a callable (pose, t) -> body velocity, got {drift!r}")
    return gait


def _cell_parameters(eta, alpha, phase0, stationary_start: bool, batch: tuple[int, ...],
                     dtype, device) -> tuple[Tensor, Tensor, Tensor]:
    """``eta``, ``alpha`` and ``phase0`` per batch cell, flat ``(B,)``; refuses negative
    ``eta`` or ``alpha``, and ``alpha = 0`` with a stationary start."""
    eta_c = per_cell(eta, "eta", batch, dtype, device)
    alpha_c = per_cell(alpha, "alpha", batch, dtype, device)
    phase0_c = per_cell(phase0, "phase0", batch, dtype, device)
    if (eta_c < 0).any():
        raise ValueError("eta must be >= 0")
    if (alpha_c < 0).any():
        raise ValueError("alpha must be >= 0")
    if stationary_start and (alpha_c <= 0).any():
        raise ValueError(
            "stationary_start needs alpha > 0 (the stationary law N(0, η²/(2α)) does not exist "
            "for alpha = 0); pass stationary_start=False"
        )
    return eta_c, alpha_c, phase0_c


def interval_power(system: LocomotionSystem, r: Tensor, dt: float) -> Tensor:
    """The power channel of recorded shapes, on the sample intervals (docs/conventions.md).

    Row ``k`` is ``v_kᵀ M(r̄_k) v_k`` with ``v_k = (r_{k+1} − r_k)/Δt`` and
    ``r̄_k = (r_k + r_{k+1})/2``: the power of the interval's mean shape velocity, the quantity a
    regression can match from the samples alone. The last row is NaN.

    Args:
        system: the system whose metric ``M(r)`` dissipates the power.
        r: ``(..., T, d)`` true shapes at the sample times (``T ≥ 1``).
        dt: sampling interval ``Δt > 0``.

    Returns:
        ``(..., T)`` power, NaN in the last row (and wherever ``r`` is NaN at either end).
    """
    if not isinstance(r, Tensor) or r.ndim < 2 or r.shape[-1] != system.shape_dim:
        raise ValueError(f"interval_power: r must be a tensor (..., T, {system.shape_dim}), got "
                         f"{tuple(r.shape) if isinstance(r, Tensor) else type(r).__name__}")
    if not dt > 0:
        raise ValueError(f"interval_power: dt must be positive, got {dt!r}")
    v = (r[..., 1:, :] - r[..., :-1, :]) / dt
    m = system.metric(0.5 * (r[..., 1:, :] + r[..., :-1, :]))
    p = ((m @ v.unsqueeze(-1)).squeeze(-1) * v).sum(-1)
    return torch.cat([p, p.new_full(p.shape[:-1] + (1,), float("nan"))], -1)


# ---------------------------------------------------------------------------- integrator
def _integrate(
    system: LocomotionSystem,
    gait,
    *,
    eta: Tensor,
    alpha: Tensor,
    phase0: Tensor,
    delta0: Tensor,
    noise: Callable[[int], Tensor],
    n_samples: int,
    dt: float,
    substeps: int,
    drift: Drift | None = None,
    batch: Sequence[int] | None = None,
) -> dict[str, Tensor]:
    """Integrate ``B`` cells and return the recorded arrays, shaped ``batch + (T, ...)``.

    Args:
        eta, alpha, phase0: ``(B,)`` per-cell parameters.
        delta0: ``(B, d)`` shape offset at the start ``t = −Δt/2``.
        noise: ``n -> (B, n, 1 + d)`` standard normal draws for the next ``n`` fine steps
            (column 0 drives the phase, columns 1: the joints); called block by block in order.
        n_samples: ``T``; ``dt``: sampling interval; ``substeps``: fine steps per sample (even).
        batch: shape to give the ``B`` cells (default ``(B,)``).
    """
    B, d = delta0.shape
    batch = tuple(batch) if batch is not None else (B,)
    S, half = substeps, substeps // 2
    h = dt / S
    sqrt_h = math.sqrt(h)
    eta_, alpha_ = eta[:, None], alpha[:, None]
    per_draw = max(1, _BLOCK_FINE_STEPS // S)  # recording intervals per noise draw
    per_block = per_draw * max(1, _STEP_FINE_STEPS // (per_draw * S))  # ... per integration block
    kw = dict(dtype=delta0.dtype, device=delta0.device)
    # Heun's step for dδ = −αδ dt + η dW with its linear drift is the linear map
    # δ_{n+1} = c δ_n + e ΔW_n (predictor δ + f(δ)h + ΔW, corrector δ + ½(f(δ) + f(pred))h + ΔW)
    ah = alpha_ * h
    heun_c, heun_e = 1 - ah + 0.5 * ah * ah, 1 - 0.5 * ah  # (B, 1)

    def draw(n: int) -> Tensor:
        z = noise(n)
        if tuple(z.shape) != (B, n, d + 1):
            raise RuntimeError(f"noise source returned shape {tuple(z.shape)}, "
                               f"expected {(B, n, d + 1)}")
        return z

    # state at the current fine point
    t_now = -dt / 2
    phi = phase0 - dt / 2
    delta = delta0
    r = gait(phi) + delta
    a_now = system.connection(r)
    pose = torch.zeros(B, 3, **kw)

    T = n_samples
    out = {"phase": (T,), "delta": (T, d), "r": (T, d), "pose": (T, 3), "xi": (T, 3),
           "r_dot": (T, d)}
    out = {k: torch.empty((B,) + shape, **kw) for k, shape in out.items()}  # recorded samples
    for k0 in range(0, n_samples, per_block):
        n_int = min(per_block, n_samples - k0)
        K = n_int * S
        z = torch.cat([draw(min(per_draw, k0 + n_int - j) * S)
                       for j in range(k0, k0 + n_int, per_draw)], 1)
        dw = z * (eta_[..., None] * sqrt_h)  # η dW: (B, K, 1 + d)

        # shape process: φ exact, δ by Heun (both have additive noise)
        phis = phi[:, None] + torch.cumsum(h + dw[..., 0], -1)
        delta_start = delta
        deltas = _heun_offsets(delta, dw[..., 1:], heun_c, heun_e)  # (B, K, d)
        delta = deltas[:, -1]
        rs_new = gait(phis) + deltas  # (B, K, d)
        a_new = system.connection(rs_new)

        # fine points 0..K of the block (point 0 is the carried state)
        rs = torch.cat([r[:, None], rs_new], 1)
        a_all = torch.cat([a_now[:, None], a_new], 1)
        dr = rs[:, 1:] - rs[:, :-1]  # (B, K, d)
        a_bar = 0.5 * (a_all[:, 1:] + a_all[:, :-1])
        # tiny matrix-vector products: elementwise sums beat batched matmul here
        twist = (a_bar * dr[..., None, :]).sum(-1)  # (B, K, 3)

        if drift is None:
            poses = se2.accumulate(se2.exp(twist), pose)  # (B, K + 1, 3)
        elif getattr(drift, "heading_only", False):
            twist, poses = _heading_drifted_poses(twist, pose, drift, t_now, h, batch)
        else:
            twist, poses = _drifted_poses(twist, pose, drift, t_now, h, batch)

        # record: sample j sits at fine point j S + S/2 of the block
        sl, rows = slice(half, K, S), slice(k0, k0 + n_int)
        out["phase"][:, rows] = torch.cat([phi[:, None], phis], 1)[:, sl]
        out["delta"][:, rows] = torch.cat([delta_start[:, None], deltas], 1)[:, sl]
        out["r"][:, rows] = rs[:, sl]
        out["pose"][:, rows] = poses[:, sl]
        out["xi"][:, rows] = twist.reshape(B, n_int, S, 3).sum(2) / dt
        out["r_dot"][:, rows] = (rs[:, S::S] - rs[:, 0:K:S]) / dt

        # carry the block's last fine point
        t_now += K * h
        phi, r, pose = phis[:, -1].clone(), rs[:, -1].clone(), poses[:, -1].clone()
        a_now = a_new[:, -1].clone()

    return {k: v.reshape(batch + v.shape[1:]) for k, v in out.items()}


def _heun_offsets(delta0: Tensor, dw: Tensor, c: Tensor, e: Tensor) -> Tensor:
    """Offsets ``δ_1 … δ_K`` of the linear recurrence ``δ_{n+1} = c δ_n + e ΔW_n``.

    Evaluated for the whole block at once by a parallel scan (log depth, no Python step per
    fine step). ``delta0 (B, d)``, ``dw (B, K, d)``, ``c, e (B, 1)`` -> ``(B, K, d)``.
    """
    u = (e[:, None] * dw).movedim(1, 0)  # (K, B, d)
    cs = c[None]  # (1, B, 1): every step's factor, shared (composed once per scan round)

    def combine(first, then):
        return then[0] * first[0], then[0] * first[1] + then[1]

    def apply(state, step):
        return (step[0] * state[0] + step[1],)

    (states,) = scan_states(combine, apply, (delta0,), (cs, u))  # (K + 1, B, d)
    return states[1:].movedim(0, 1)


def _drifted_poses(
    twist: Tensor, pose: Tensor, drift: Drift, t0: float, h: float, batch: tuple[int, ...]
) -> tuple[Tensor, Tensor]:
    """Pose steps with an extra body velocity ``drift(g, t)``, by Heun, one fine step at a time.

    Args:
        twist: ``(B, K, 3)`` connection part of each step's twist; ``pose``: ``(B, 3)`` start.
    Returns:
        the full twists ``(B, K, 3)`` (drift included) and the poses ``(B, K + 1, 3)``.
    """
    B, K, _ = twist.shape

    def call(g: Tensor, t: float) -> Tensor:
        v = drift(g.reshape(batch + (3,)), t)
        if not isinstance(v, Tensor):
            raise TypeError(f"drift must return a tensor of shape {batch + (3,)}, got "
                            f"{type(v).__name__}")
        try:
            return torch.broadcast_to(v, batch + (3,)).reshape(B, 3).to(twist.dtype)
        except RuntimeError:
            raise ValueError(f"drift must return a body velocity of shape {batch + (3,)}, "
                             f"got {tuple(v.shape)}") from None

    poses, twists = [pose], []
    for n in range(K):
        t = t0 + n * h
        v0 = call(pose, t)
        pred = se2.compose(pose, se2.exp(twist[:, n] + v0 * h))
        step = twist[:, n] + 0.5 * (v0 + call(pred, t + h)) * h
        pose = se2.compose(pose, se2.exp(step))
        poses.append(pose)
        twists.append(step)
    return torch.stack(twists, 1), torch.stack(poses, 1)


def _heading_drifted_poses(
    twist: Tensor, pose: Tensor, drift: Drift, t0: float, h: float, batch: tuple[int, ...]
) -> tuple[Tensor, Tensor]:
    """:func:`_drifted_poses` for a ``heading_only`` drift, vectorised over the block.

    The drift's ω does not depend on the pose, so the headings of all fine points follow from
    a cumulative sum first; the drift is then evaluated at every fine point's heading at once
    and averaged over each step (Heun). With a drift whose ω is constant in time this is the
    same scheme as the step-by-step loop (its predictor heading equals the corrector's).
    """
    B, K, _ = twist.shape
    t = t0 + h * torch.arange(K + 1, dtype=twist.dtype, device=twist.device)

    def call(theta: Tensor) -> Tensor:
        nan = torch.full_like(theta, float("nan"))
        g = torch.stack([nan, nan, theta], -1).reshape(batch + (K + 1, 3))
        v = drift(g, t)
        if not isinstance(v, Tensor):
            raise TypeError(f"drift must return a tensor of shape {batch + (K + 1, 3)}, got "
                            f"{type(v).__name__}")
        try:
            return torch.broadcast_to(v, batch + (K + 1, 3)).reshape(B, K + 1, 3).to(twist.dtype)
        except RuntimeError:
            raise ValueError(f"a heading_only drift must return body velocities of shape "
                             f"{batch + (K + 1, 3)} for poses of that shape, got "
                             f"{tuple(v.shape)}") from None

    # ω of the drift does not depend on the heading: any heading gives it
    w = call(pose[:, 2:3].expand(B, K + 1).clone())[..., 2]
    theta = pose[:, 2:3] + torch.cat(
        [torch.zeros_like(w[:, :1]), torch.cumsum(twist[..., 2] + 0.5 * (w[:, 1:] + w[:, :-1]) * h,
                                                  -1)], -1)
    v = call(theta)
    step = twist + 0.5 * (v[:, 1:] + v[:, :-1]) * h
    return step, se2.accumulate(se2.exp(step), pose)
