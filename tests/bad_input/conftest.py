from pathlib import Path

import numpy as np
import pytest

from torchconn.io.trajectory_files import write_csv
from torchconn.physics.gaits import reference_gait
from torchconn.physics.systems import NLinkSwimmer
from torchconn.simulation.rollout import simulate


@pytest.fixture(scope="session")
def recording(tmp_path_factory) -> Path:
    """A valid 3-link recording: one trial, 6 cycles, 32 samples per cycle, with power."""
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=6,
                    samples_per_cycle=32, substeps=4, seeds=[1])
    path = tmp_path_factory.mktemp("data") / "good.csv"
    write_csv(traj[0] if traj.batch_shape else traj, path)
    return path


@pytest.fixture(scope="session")
def table(recording) -> tuple[list[str], np.ndarray]:
    """The recording's header and values (NaN for its empty cells)."""
    rows = recording.read_text().splitlines()
    values = np.array([[float(v) if v else np.nan for v in r.split(",")] for r in rows[1:]])
    return rows[0].split(","), values
