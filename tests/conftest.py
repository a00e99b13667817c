"""Shared set-up: one intra-op thread, the ``numerics`` marker, and recordings that tests in
several folders use."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, simulate
from torchconn.improve import (
    circle_gait,
)
from torchconn.io.trajectory_files import write_csv
from torchconn.simulation.observe import observe

from .recordings import wave_gait
from .regression.common import clean_circle_trials

# The suite is made of small batched tensor ops, for which one intra-op thread is fastest and
# keeps timings steady on a shared 2-core machine.
torch.set_num_threads(1)

TESTS = Path(__file__).resolve().parent

#: the numerics tests (factorisations, regressions, smoothing, phase), as paths under tests/: a
#: file, or a folder ending in "/" for every file under it. Marked ``numerics`` and run again on
#: MKL's AVX2 code path by tests/test_mkl_code_paths.py.
NUMERICS = {
    "test_linalg.py",
    "test_scipy_crosschecks.py",
    "phase/",
    "regression/metric/",
    "regression/selection/",
    "regression/test_binning.py",
    "regression/test_connection.py",
    "regression/test_diagnostics.py",
}


def _is_numerics(path: Path) -> bool:
    if not path.is_relative_to(TESTS):
        return False
    name = path.relative_to(TESTS).as_posix()
    return any(name == entry or (entry.endswith("/") and name.startswith(entry))
               for entry in NUMERICS)


def pytest_collection_modifyitems(items):
    for item in items:
        if _is_numerics(item.path.resolve()):
            item.add_marker(pytest.mark.numerics)


SPC = 12  # samples per cycle: a video rate
CYCLES = (9, 14, 20)
#: lost runs (first sample, end) of each recording, beside 2 % scattered drop-outs
GAPS = ({(0, 3)}, {(5 * SPC + 1, 5 * SPC + 5)}, {(7 * SPC, 7 * SPC + 4), (-2, None)})


def _recording(k: int, seed: int):
    seeds = [seed + k]
    traj = simulate(NLinkSwimmer(5), wave_gait(), eta=0.025, n_cycles=CYCLES[k],
                    samples_per_cycle=SPC, seeds=seeds)
    traj = observe(traj, 0.005, dropout=0.02, seeds=seeds)
    pose, r, power = traj.pose.clone(), traj.r.clone(), traj.power.clone()
    for a, b in GAPS[k]:
        pose[:, a:b] = r[:, a:b] = power[:, a:b] = math.nan
    return traj.with_fields(pose=pose, r=r, power=power, truth=None)


def _files(directory, seed: int = 0) -> list:
    return [write_csv(_recording(k, seed), directory / f"tank{k}.csv") for k in range(3)]


@pytest.fixture(scope="module")
def unequal_recordings(tmp_path_factory):
    """Three simulated 5-link recordings at a video rate (12 samples per cycle) of 9, 14 and 20
    cycles, each with its own pattern of lost samples (its first samples, a run in the middle,
    its last samples, scattered drop-outs), in one CSV each: read together they are NaN-padded
    to the longest on one grid."""
    return _files(tmp_path_factory.mktemp("tank"))


@pytest.fixture(scope="module")
def clean30():
    """4 trials x 30 cycles of the 3-link on a circle, noise-free."""
    return clean_circle_trials()


@pytest.fixture(scope="module")
def fitted_3link():
    """A pooled model of the 3-link on a circle of radius 0.5 (4 trials x 20 cycles, clean)."""
    system = NLinkSwimmer(3)
    traj = simulate(system, circle_gait(2, 0.5), eta=0.025, n_cycles=20, seeds=np.arange(4) + 50)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        no_power = traj.with_fields(power=None)
        est = ConnectionEstimator(pool=True).fit(no_power)
    return system, traj, est.model_


_AVX2_TEST = "test_mkl_code_paths.py::test_numerics_pass_on_mkls_avx2_code_path"


def pytest_collection_finish(session):
    """Start the numerics run on MKL's AVX2 path (tests/test_mkl_code_paths.py) at once
    where its test is selected, so that it runs beside the suite, not after it."""
    for item in session.items:
        if item.nodeid.endswith(_AVX2_TEST):
            item.module.start()


def pytest_sessionfinish(session):
    """End that run if the suite ended without waiting for it (interrupted, -x)."""
    for item in getattr(session, "items", []):
        if item.nodeid.endswith(_AVX2_TEST):
            item.module.stop()
