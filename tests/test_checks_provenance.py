"""The shared input checks (torchconn._checks) and provenance helpers (torchconn._provenance)."""

import json
import os

import matplotlib
import numpy as np
import pytest
import scipy
import torch

from torchconn import _checks, _provenance
from torchconn.phase.fourier import fit_fourier
from torchconn.phase.limit_cycle import fit_limit_cycle
from torchconn.physics import se2
from torchconn.physics.systems import NLinkSwimmer

# ------------------------------------------------------------------------------ checks


def test_tensor_check_names_function_argument_expectation_and_what_came():
    with pytest.raises(TypeError, match=r"^f: x must be a torch.Tensor of shape \(\.\.\., T\), got list$"):
        _checks.tensor([1.0], "x", "(..., T)", fn="f")
    with pytest.raises(TypeError, match=r"floating-point torch.Tensor .* got torch.int64 tensor of "
                                        r"shape \(3,\)"):
        _checks.tensor(torch.arange(3), "x", "(..., T)", floating=True)
    with pytest.raises(ValueError, match=r"^x must have shape \(\.\.\., T\) with T >= 4, got \(3,\)$"):
        _checks.tensor(torch.zeros(3), "x", "(..., T) with T >= 4", valid=lambda t: t.shape[-1] >= 4)
    x = torch.zeros(2, 5)
    assert _checks.tensor(x, "x", "(..., T)") is x


def test_finite_integer_and_last_dim():
    x = torch.tensor([0.0, float("nan"), 1.0])
    with pytest.raises(ValueError, match="x contains NaN or inf; drop them"):
        _checks.finite(x, "x", hint="drop them")
    assert _checks.finite(x, "x", nan_ok=True) is x
    with pytest.raises(ValueError, match="g: x contains ±inf"):
        _checks.finite(torch.tensor([float("inf")]), "x", fn="g", nan_ok=True)
    assert _checks.integer(np.int64(3), "n", minimum=1) == 3
    for bad in (True, 2.0, "3", 0):
        with pytest.raises(ValueError, match=r"n must be an integer >= 1, got"):
            _checks.integer(bad, "n", minimum=1)
    with pytest.raises(ValueError, match=r"g must have shape \(\.\.\., 3\), got \(2, 2\)"):
        _checks.last_dim(torch.zeros(2, 2), 3, "g")


def test_phase_samples_both_modes():
    phase, r = torch.zeros(2, 10), torch.zeros(2, 10, 3)
    _checks.phase_samples(phase, r, r, d=3, same_batch=True)
    _checks.phase_samples(phase[0], r, r)  # T matches, batch left to broadcasting
    with pytest.raises(ValueError, match=r"r must have shape phase.shape \+ \(2,\) = \(2, 10, 2\) "
                                         r"for a 2-joint model, got \(2, 10, 3\)"):
        _checks.phase_samples(phase, r, r, d=2, same_batch=True, why=" for a 2-joint model")
    with pytest.raises(ValueError, match=r"f: r_dot must have the same shape as r \(2, 10, 3\)"):
        _checks.phase_samples(phase, r, r[:, :5], fn="f")
    with pytest.raises(TypeError, match="f: phase must be a torch.Tensor"):
        _checks.phase_samples(None, r, r, fn="f")


def test_the_stages_use_the_shared_checks():
    # one wording across stages: the function, the argument, the expected shape, what came
    with pytest.raises(TypeError, match=r"xi must be a torch.Tensor of shape \(\.\.\., 3\), got list"):
        se2.exp([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"r must have shape \(\.\.\., 2\) for a system with 2 joints"):
        NLinkSwimmer(3).connection(torch.zeros(4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="fit_fourier: order must be an integer >= 0"):
        fit_fourier(torch.zeros(20), torch.zeros(20), -1)
    with pytest.raises(ValueError, match=r"fit_limit_cycle: r must have shape \(\.\.\., T=50, d\)"):
        fit_limit_cycle(torch.zeros(50), torch.zeros(40, 2), torch.zeros(40, 2))


# -------------------------------------------------------------------------- provenance


def test_spawn_seeds_are_seed_sequence_children_keyed_by_position():
    seeds = _provenance.spawn_seeds(7, (2, 3), key=(4,))
    assert seeds.shape == (2, 3) and seeds.dtype == object
    for (i, j), s in np.ndenumerate(seeds):
        state = np.random.SeedSequence(7, spawn_key=(4, i, j)).generate_state(1, np.uint64)[0]
        assert s == int(state) >> 1 and isinstance(s, int)
    # a cell's seed does not depend on the shape of the grid it sits in
    assert _provenance.spawn_seeds(7, (5, 1), key=(4,))[1, 0] == seeds[1, 0]


def test_versions_and_source_hash():
    v = _provenance.versions()
    assert v["torch"] == torch.__version__ and v["numpy"] == np.__version__
    assert v["scipy"] == scipy.__version__ and v["matplotlib"] == matplotlib.__version__
    assert {"torchconn", "python", "scipy", "matplotlib"} <= set(v)
    h = _provenance.source_hash()
    assert len(h) == 16 and int(h, 16) >= 0


def test_sidecar_is_json_with_provenance_and_atomic(tmp_path, monkeypatch):
    path = tmp_path / "sub" / "run.json"
    payload = {"a": torch.tensor([1.0, float("nan")]), "b": np.float64(2.5), 3: (1, 2),
               "p": tmp_path}
    _provenance.write_sidecar(path, payload)
    got = json.loads(path.read_text())
    assert got["a"] == [1.0, None] and got["b"] == 2.5 and got["3"] == [1, 2]
    assert got["p"] == str(tmp_path)
    assert got["source_hash"] == _provenance.source_hash() and "versions" in got

    # a failure while replacing leaves the previous file intact and no temporary behind
    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        _provenance.write_sidecar(path, {"a": 1})
    assert json.loads(path.read_text())["b"] == 2.5
    assert sorted(p.name for p in path.parent.iterdir()) == ["run.json"]
