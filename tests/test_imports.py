"""What importing the package and its commands loads: ``import torchconn`` no heavy library and
no pipeline stage, each public name on first use, and a command only what it uses (each
check in a fresh interpreter)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: libraries too heavy to load on ``import torchconn`` (scipy's statistics and optimisers,
#: plotting, data frames, the symbolic maths and the compiler torch loads on demand)
HEAVY = ("scipy", "matplotlib", "pandas", "sympy", "torch._dynamo")


def _loaded(code: str) -> set[str]:
    """The modules loaded after running ``code`` in a fresh interpreter."""
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json\n"
                          "print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True).stdout
    return set(json.loads(out.splitlines()[-1]))


def _heavy(loaded: set[str]) -> list[str]:
    return sorted(m for m in loaded if m in HEAVY or m.startswith(tuple(h + "." for h in HEAVY)))


def test_import_torchconn_loads_no_heavy_library_and_no_stage():
    loaded = _loaded("import torchconn")
    assert not _heavy(loaded)
    stages = {"regression", "phase", "simulation", "physics", "noise", "evaluation", "sweep",
              "discrepancy", "improve"}
    assert not {m.split(".")[1] for m in loaded if m.startswith("torchconn.")} & stages


@pytest.mark.parametrize("package", ["torchconn.discrepancy", "torchconn.sweep",
                                     "torchconn.regression", "torchconn.fit",
                                     "torchconn.convert"])
def test_a_package_or_command_loads_no_heavy_library_at_import(package):
    assert not _heavy(_loaded(f"import {package}"))


def test_every_public_name_is_importable_from_the_package():
    code = ("import torchconn\n"
            "from torchconn import *\n"
            "missing = [n for n in torchconn.__all__ if n not in globals()]\n"
            "absent = [n for n in torchconn.__all__ if n not in dir(torchconn)]\n"
            "assert not missing and not absent, (missing, absent)\n"
            "from torchconn import ConnectionEstimator, Trajectory, gaits, se2\n"
            "assert ConnectionEstimator.__module__ == 'torchconn.regression.estimator'\n"
            "assert gaits.__name__ == 'torchconn.physics.gaits'\n"
            "assert se2.__name__ == 'torchconn.physics.se2'\n")
    _loaded(code)  # raises on a failed assertion (check=True)


@pytest.mark.parametrize("package", ["torchconn", "torchconn.discrepancy", "torchconn.sweep"])
def test_lazy_packages_give_every_name_of_all(package):
    import importlib

    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    assert set(module.__all__) <= set(dir(module))


def test_subpackages_are_attributes_and_unknown_names_raise_attribute_error():
    import torchconn

    assert torchconn.datasets.prickleback().name == "prickleback"
    assert torchconn.regression.selection.COMPONENTS == ("v_x", "v_y", "omega")
    with pytest.raises(AttributeError, match="no attribute 'no_such_thing'"):
        torchconn.no_such_thing  # noqa: B018
    assert not hasattr(torchconn, "__wrapped__")


def test_trajectory_from_movement_is_ready_without_importing_io():
    """``Trajectory.from_movement`` converts through the tracking module, which ``import
    torchconn`` sets up however the class is reached."""
    loaded = _loaded("from torchconn.trajectory import Trajectory, _from_movement\n"
                     "assert _from_movement is not None")
    assert "torchconn.io.tracking.convert" in loaded


def test_fit_without_figures_loads_no_plotting(tmp_path):
    """``torchconn-fit --no-figures`` draws nothing and loads no matplotlib; no fit loads
    torch's compiler or sympy (forward-mode derivatives with a constant operand would)."""
    code = (
        "import numpy as np\n"
        "from torchconn import NLinkSwimmer, simulate, write_csv\n"
        "from torchconn.fit import main\n"
        "from torchconn.physics.gaits import reference_gait\n"
        "traj = simulate(NLinkSwimmer(3), reference_gait('3link'), eta=0.025, n_cycles=12,\n"
        "                seeds=np.array([3]))\n"
        f"path = write_csv(traj, {str(tmp_path / 'rec.csv')!r})\n"
        f"assert main([str(path), '--out', {str(tmp_path / 'fit')!r}, '--no-figures',\n"
        "             '--quiet']) == 0\n")
    loaded = _loaded(code)
    assert (tmp_path / "fit" / "report.html").exists()
    assert not {"matplotlib", "torch._dynamo", "sympy"} & loaded
