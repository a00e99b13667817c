"""``python -m torchconn.fit`` on CSV recordings in the trajectory file format."""

import csv

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.fit import main
from torchconn.io.trajectory_files import write_csv
from torchconn.physics.gaits import reference_gait
from torchconn.regression.model import LocalConnectionModel
from torchconn.simulation.observe import observe


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    seeds = np.array([3, 4])
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=20,
                    seeds=seeds)
    traj = observe(traj, 0.0, dropout=0.02, seeds=seeds)  # marker drop-outs, no jitter
    path = tmp_path_factory.mktemp("data") / "trials.csv"
    write_csv(traj, path)
    return path


def test_fit_writes_model_table_and_plots(recording, tmp_path):
    out = tmp_path / "fit"
    assert main([str(recording), "--links", "3", "--out", str(out), "--grid", "50"]) == 0
    with (out / "connection.csv").open() as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    expected = (["phase", "r1", "r2"] + [f"A_{k}_{i}" for k in ("x", "y", "theta") for i in (1, 2)]
                + [f"dA_{k}_{i}_{j}" for k in ("x", "y", "theta") for i in (1, 2) for j in (1, 2)]
                + [f"M_{i}_{j}" for i in (1, 2) for j in (1, 2)]
                + ["M_gamma_dot_1", "M_gamma_dot_2", "power_on_cycle"])
    assert header == expected
    assert len(rows) == 51
    table = np.array(rows[1:], dtype=float)
    # the fitted connection along the fitted cycle is close to the simulator's there
    swimmer = NLinkSwimmer(3)
    a_true = swimmer.connection(torch.tensor(table[:, 1:3])).reshape(50, -1).numpy()
    assert np.abs(table[:, 3:9] - a_true).max() < 0.03
    model = LocalConnectionModel.load(out / "model.npz")
    assert model.batch_shape == ()
    # M̂γ̇ and the on-cycle power against the swimmer's exact metric on the fitted cycle
    phi = torch.tensor(table[:, 0])
    gd = model.gamma_dot_at(phi)
    m_true = swimmer.metric(torch.tensor(table[:, 1:3]))
    mgd_true = (m_true @ gd[..., None])[..., 0].numpy()
    p_true = (gd.numpy() * mgd_true).sum(-1)
    assert np.sqrt(((table[:, -3:-1] - mgd_true) ** 2).sum(-1).mean()
                   / (mgd_true**2).sum(-1).mean()) < 0.02
    assert np.sqrt(((table[:, -1] - p_true) ** 2).mean() / (p_true**2).mean()) < 0.01
    for name in ("connection.png", "limit_cycle.png", "metric.png"):
        assert (out / name).stat().st_size > 1000


def test_fit_rejects_the_wrong_number_of_links(recording, tmp_path, capsys):
    assert main([str(recording), "--links", "5", "--out", str(tmp_path / "x")]) == 2
    assert "joint" in capsys.readouterr().err
