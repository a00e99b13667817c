"""The commands' manners (issue 34): warnings in one format on stderr, ``--links`` from the
inputs, ``improve propose`` on tracking files, and the API and the commands fitting with one
estimator."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest
import torch

import torchconn
from torchconn import NLinkSwimmer, simulate, write_csv
from torchconn.cli.conversion import TRACKING_LINKS
from torchconn.convert import main as convert_main
from torchconn.fit import main as fit_main
from torchconn.improve.__main__ import main as improve_main
from torchconn.improve.loop import circle_gait
from torchconn.io.trajectory_files import read_csv
from torchconn.physics.gaits import reference_gait
from torchconn.regression.defaults import pooled_estimator
from torchconn.regression.estimator import ConnectionEstimator
from torchconn.regression.model import LocalConnectionModel
from torchconn.testing.tracking import render_keypoints, write_sleap_csv

PACKAGE = Path(torchconn.__file__).parent


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Two 3-link trials of 20 cycles (joint columns r1, r2)."""
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=20,
                    seeds=np.array([3, 4]))
    return write_csv(traj, tmp_path_factory.mktemp("data") / "trials.csv")


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A SLEAP CSV of a 3-link swimmer, 10 keypoints, 12 cycles at 30 frames per second."""
    traj = simulate(NLinkSwimmer(3), circle_gait(2, 0.8), eta=0.025, n_cycles=12,
                    seeds=np.array([2]))
    return write_sleap_csv(render_keypoints(traj, NLinkSwimmer(3), per_link=3, seed=5)[0],
                           tmp_path_factory.mktemp("track") / "track.csv")


def _warning_prints(tree: ast.AST) -> list[int]:
    """Lines of ``print`` calls whose text speaks of a warning."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
            text = " ".join(c.value for c in ast.walk(node)
                            if isinstance(c, ast.Constant) and isinstance(c.value, str))
            if "warning" in text.lower():
                found.append(node.lineno)
    return found


def test_no_print_call_gives_a_warning():
    """Warnings go through ``warnings.warn``; the one ``print`` of them is run_command's, which
    writes every warning as ``prog: warning: ...`` on stderr."""
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = _warning_prints(ast.parse(path.read_text(), str(path)))
        if lines:
            offenders[str(path.relative_to(PACKAGE))] = lines
    assert list(offenders) == ["_cli.py"] and len(offenders["_cli.py"]) == 1, offenders
    # the detector finds the kind it is for
    assert _warning_prints(ast.parse('print("WARNING: the model loses")')) == [1]


def test_the_checks_warnings_go_to_stderr_even_when_quiet(recording, tmp_path, capsys):
    # every 8th sample: 8 samples per gait cycle, fewer than the checks ask for
    traj = read_csv(recording)
    sparse = traj.with_fields(t=traj.t[::8], pose=traj.pose[:, ::8], r=traj.r[:, ::8],
                              power=None)
    path = write_csv(sparse, tmp_path / "sparse.csv")
    fit_main([str(path), "--out", str(tmp_path / "fit"), "--quiet", "--no-figures"])
    out, err = capsys.readouterr()
    assert out == ""
    assert "torchconn-fit: warning: only 8 samples per gait cycle" in err


def test_links_come_from_the_joint_columns_of_trajectory_csvs(recording, tmp_path, capsys):
    given, inferred = tmp_path / "given", tmp_path / "inferred"
    assert fit_main([str(recording), "--links", "3", "--out", str(given), "--no-figures",
                     "--quiet"]) == 0
    assert fit_main([str(recording), "--out", str(inferred), "--no-figures"]) == 0
    assert "--links 3, from the joint columns r1..r2" in capsys.readouterr().out
    assert (inferred / "connection.csv").read_bytes() == (given / "connection.csv").read_bytes()


def test_links_cannot_be_inferred_from_csvs_of_different_bodies(recording, tmp_path, capsys):
    five = simulate(NLinkSwimmer(5), circle_gait(4, 0.5),
                    eta=0.025, n_cycles=4, seeds=np.array([1]))
    other = write_csv(five, tmp_path / "five.csv")
    out = tmp_path / "fit"
    assert fit_main([str(recording), str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot infer --links" in err and f"{recording}: 2" in err and f"{other}: 4" in err
    assert "Pass --links N" in err and not out.exists()


def test_tracking_files_get_the_documented_default_and_guidance(tracked, tmp_path, capsys):
    out = tmp_path / "converted"
    assert convert_main([str(tracked), "--fps", "30", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"--links {TRACKING_LINKS}, the default for tracking files" in said
    assert "K keypoints along the body track at most K - 1 links" in said
    assert read_csv(out / "track.csv").shape_dim == TRACKING_LINKS - 1
    with pytest.raises(SystemExit):
        convert_main(["--help"])
    assert "with 8 keypoints, 7 or 5" in " ".join(capsys.readouterr().out.split())


def test_improve_propose_reads_tracking_files_as_fit_does(tracked, tmp_path, capsys):
    """A tracking file proposes the gait its conversion by torchconn-convert proposes."""
    flags = ["--links", "3", "--fps", "30", "--curve", "polyline"]
    assert convert_main([str(tracked), *flags, "--out", str(tmp_path / "csv"), "--quiet"]) == 0
    runs = {}
    for name, data, options in (("tracked", tracked, flags),
                                ("converted", tmp_path / "csv" / "track.csv", [])):
        out = tmp_path / name
        assert improve_main(["propose", str(data), *options, "--out", str(out), "--quiet",
                             "--no-figures"]) == 0
        runs[name] = out
    assert capsys.readouterr().out == ""
    for name in ("next_gait.csv", "report.json"):
        a, b = ((runs[k] / name).read_text() for k in ("tracked", "converted"))
        if name == "report.json":  # the inputs' names differ
            a, b = ({k: v for k, v in json.loads(x).items() if k not in ("data", "provenance")}
                    for x in (a, b))
        assert a == b, name
    # a conversion flag given for trajectory CSVs is warned about, as by fit
    assert improve_main(["propose", str(tmp_path / "csv" / "track.csv"), "--fps", "30",
                         "--out", str(tmp_path / "again"), "--quiet"]) == 0
    assert "torchconn-improve propose: warning: --fps ignored" in capsys.readouterr().err


def test_python_and_the_command_fit_one_file_to_the_same_numbers(recording, tmp_path):
    """torchconn-fit's estimator is pooled_estimator(): ConnectionEstimator's defaults with
    the trials pooled, the one setting in which it differs from ConnectionEstimator()."""
    out = tmp_path / "fit"
    assert fit_main([str(recording), "--out", str(out), "--no-figures", "--quiet"]) == 0
    shell = LocalConnectionModel.load(out / "model.npz")
    python = pooled_estimator().fit(read_csv(recording)).model_
    for name in ("A", "dA", "c", "b", "M"):
        assert torch.equal(getattr(shell, name).coeffs, getattr(python, name).coeffs), name
    assert pooled_estimator().get_params() == ConnectionEstimator(pool=True).get_params()
    defaults = ConnectionEstimator().get_params()
    differs = {k for k, v in pooled_estimator().get_params().items() if defaults[k] != v}
    assert differs == {"pool"}
