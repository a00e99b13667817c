"""The scaffold the five commands share (torchconn.cli): --version, --quiet, --no-figures,
--threads and --device, and no command loading another command's package."""

import json
import subprocess
import sys

import numpy as np
import pytest

import torchconn
from torchconn import NLinkSwimmer, simulate, write_csv
from torchconn.convert import main as convert_main
from torchconn.discrepancy.__main__ import main as discrepancy_main
from torchconn.fit import main as fit_main
from torchconn.improve.__main__ import main as improve_main
from torchconn.improve.loop import circle_gait
from torchconn.sweep.__main__ import main as sweep_main

#: command -> (its main, the argv that reaches its working parser, the flags it must offer)
WORK = ["--quiet", "--no-figures", "--threads"]  # --no-figures a no-op where none are drawn
COMMANDS = {
    "fit": (fit_main, [], WORK + ["--device"]),
    "convert": (convert_main, [], WORK),  # conversion runs on the CPU
    "discrepancy": (discrepancy_main, [], WORK + ["--device"]),
    "improve simulate": (improve_main, ["simulate"], WORK + ["--device"]),
    "improve propose": (improve_main, ["propose"], WORK + ["--device"]),
    "sweep": (sweep_main, [], WORK + ["--device"]),
}
#: the module of each command, and the packages of the others
MODULES = {"torchconn.fit": "fit", "torchconn.convert": "convert",
           "torchconn.discrepancy.__main__": "discrepancy",
           "torchconn.improve.__main__": "improve", "torchconn.sweep.__main__": "sweep"}


def _written(out):
    """The names of the outputs in ``out`` (not its hidden ownership marker)."""
    return {p.name for p in out.iterdir() if not p.name.startswith(".")}


@pytest.mark.parametrize("main", [fit_main, convert_main, discrepancy_main, improve_main,
                                  sweep_main], ids=["fit", "convert", "discrepancy", "improve",
                                                    "sweep"])
def test_every_command_prints_its_version(main, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"torchconn {torchconn.__version__}\n"


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_working_command_offers_the_shared_flags(name, capsys):
    main, sub, flags = COMMANDS[name]
    with pytest.raises(SystemExit) as stop:
        main([*sub, "--help"])
    assert stop.value.code == 0
    usage = capsys.readouterr().out
    missing = [f for f in flags if f not in usage]
    assert not missing, f"{name} lacks {missing}"


@pytest.mark.parametrize("module", list(MODULES))
def test_no_command_loads_another_commands_package(module):
    others = sorted(set(MODULES.values()) - {MODULES[module]})
    code = (f"import sys, {module}\n"
            "print(' '.join(sorted({m.split('.')[1] for m in sys.modules "
            "if m.startswith('torchconn.') and m.count('.') >= 1})))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True).stdout.split()
    assert not set(loaded) & set(others), f"{module} loads {sorted(set(loaded) & set(others))}"


def test_quiet_improve_writes_all_but_prints_nothing(tmp_path, capsys):
    """``--quiet`` silences the informational lines, not the outputs; ``--no-figures`` skips
    the PNGs of ``simulate``."""
    out = tmp_path / "loop"
    assert improve_main(["simulate", "--rounds", "1", "--trials", "2", "--cycles", "8",
                         "--out", str(out), "--quiet", "--no-figures"]) == 0
    assert capsys.readouterr().out == ""
    assert _written(out) == {"rounds.csv", "run.json", "next_gait.csv", "next_gait.json",
                             "best_gait.csv", "best_gait.json",
                             "report.html"}
    traj = simulate(NLinkSwimmer(3), circle_gait(2, 0.8), eta=0.025, n_cycles=10,
                    seeds=np.arange(2))
    path = write_csv(traj, tmp_path / "rec.csv")
    assert improve_main(["propose", str(path), "--links", "3", "--out", str(tmp_path / "next"),
                         "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert (tmp_path / "next" / "next_gait.csv").exists()


def test_quiet_convert_writes_all_but_prints_nothing(tmp_path, capsys):
    from torchconn.physics.gaits import reference_gait
    from torchconn.testing.tracking import render_keypoints, write_sleap_csv

    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=8,
                    seeds=np.array([1]))
    track = write_sleap_csv(render_keypoints(traj, NLinkSwimmer(3), per_link=3, seed=5)[0],
                            tmp_path / "track.csv")
    out = tmp_path / "converted"
    assert convert_main([str(track), "--links", "3", "--fps", "30", "--curve", "polyline",
                         "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert _written(out) == {"track.csv", "convert.json"}


def test_quiet_fit_writes_all_but_prints_nothing(tmp_path, capsys):
    from torchconn.physics.gaits import reference_gait

    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=20,
                    seeds=np.array([3, 4]))
    path = write_csv(traj, tmp_path / "trials.csv")
    out = tmp_path / "fit"
    assert fit_main([str(path), "--links", "3", "--out", str(out), "--metric", "no",
                     "--no-figures", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    # the forecasting model has a file of its own where it differs from the connection
    # (here: leaning on the physics prior, the simulator's own family)
    forecast = json.loads((out / "fit.json").read_text())["forecast_model"]
    assert _written(out) == {"model.npz", "connection.csv", "fit.json", "report.html"} | (
        {"forecast_model.npz"} if forecast else set())
