"""Recordings and signals shared by the phase tests."""

import numpy as np
import torch

from torchconn import NLinkSwimmer
from torchconn.physics.gaits import reference_gait
from torchconn.simulation.observe import observe
from torchconn.simulation.rollout import simulate


def swimmer_trials(system: str, n_links: int, omega: float, seed: int, n_cycles: int = 20):
    seeds = np.random.SeedSequence(seed).generate_state(6)
    traj = simulate(NLinkSwimmer(n_links), reference_gait(system), eta=0.025, n_cycles=n_cycles,
                    seeds=seeds)
    return observe(traj, omega, seeds=seeds) if omega > 0 else traj


def periodic_signal(theta, orders, amp=1.0):
    """Sum of harmonics ``orders`` of amplitude ``amp / k`` at phases ``theta``."""
    return sum(amp / k * torch.cos(k * theta + 0.3 * k) for k in orders)
