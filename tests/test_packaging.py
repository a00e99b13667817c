"""Packaging: what the wheel holds, the packaged configs, and a wheel installed into a fresh venv
running every command from a directory outside the checkout (slow)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

import pytest

from torchconn._resources import config_names, configs, read_config
from torchconn.convert import main as convert_main
from torchconn.discrepancy.__main__ import main as discrepancy_main
from torchconn.fit import main as fit_main
from torchconn.physics.gaits import optimize
from torchconn.sweep.config import load_config, sweep_config_names

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _readme_commands() -> list[str]:
    quick = (ROOT / "README.md").read_text().split("## Quick start")[1].split("```")[1]
    return [line for line in quick.splitlines() if line.startswith("python3 -m venv")]


def test_every_subpackage_is_listed_for_the_wheel():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "torchconn").rglob("__init__.py")}
    missing = found - listed
    assert not missing, f"add {sorted(missing)} to [tool.setuptools] packages in pyproject.toml"
    assert listed - found == {"torchconn.configs"}
    assert PYPROJECT["tool"]["setuptools"]["package-dir"] == {"torchconn.configs": "configs"}
    assert (ROOT / "torchconn" / "py.typed").exists()
    # the shipped recordings and their attribution are package data
    data = PYPROJECT["tool"]["setuptools"]["package-data"]["torchconn.datasets"]
    shipped = {p.name for p in (ROOT / "torchconn" / "datasets").iterdir() if p.suffix != ".py"
               and p.name != "__pycache__"}
    assert shipped == {"XMUC02_Trial1_sleap-1.csv", "ATTRIBUTION.md"}
    assert all(any(Path(name).match(pattern) for pattern in data) for name in shipped)


def test_dependencies_are_ranges_and_the_constraints_pin_the_tested_torch():
    deps = PYPROJECT["project"]["dependencies"]
    torch_dep = next(d for d in deps if d.startswith("torch"))
    assert "==" not in torch_dep and ">=" in torch_dep
    pins = dict(line.split("==") for line in (ROOT / "constraints.txt").read_text().splitlines()
                if line and not line.startswith("#"))
    import numpy
    import scipy
    import torch

    # the pins are the versions these tests run with
    assert pins["torch"] == torch.__version__.split("+")[0]
    assert pins["numpy"] == numpy.__version__ and pins["scipy"] == scipy.__version__
    assert set(PYPROJECT["project"]["scripts"]) == {
        "torchconn-sweep", "torchconn-fit", "torchconn-discrepancy", "torchconn-convert",
        "torchconn-improve"}
    assert {"jupytext", "ipykernel", "nbconvert"} <= {re.split("[<>=]", d)[0]
                                         for d in PYPROJECT["project"]["optional-dependencies"]["notebooks"]}


def test_readme_commands_use_the_constraints_two_venvs_and_ci_runs_the_second():
    install, tests = _readme_commands()
    for cmd in (install, tests):
        assert "pip install -c constraints.txt" in cmd
    venvs = [re.search(r"python3 -m venv (\S+)", c).group(1) for c in (install, tests)]
    assert venvs[0] != venvs[1]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert ci[-1] == tests


def test_packaged_configs_resolve_by_name_and_path():
    assert {"default", "quick", "fig3", "fig4a", "fig4b", "gaits"} <= set(config_names())
    assert sweep_config_names() == ["default", "fig3", "fig4a", "fig4b", "quick"]
    assert load_config("quick").name == "quick" == load_config("quick.toml").name
    assert load_config().name == "default"
    assert load_config(ROOT / "configs" / "fig4a.toml").name == "fig4a"
    # the packaged files are the repository's configs/
    assert configs().joinpath("gaits.toml").read_text() == (ROOT / "configs" / "gaits.toml").read_text()
    with pytest.raises(ValueError, match=r"did you mean 'quick'\?\); packaged: default, fig3, "
                                         r"fig4a, fig4b, quick"):
        load_config("quik")
    with pytest.raises(ValueError, match="neither a TOML file"):
        load_config("gaits")  # packaged, but not a sweep config
    assert "nine_link_x_extremal" in read_config("gaits")


def test_bad_toml_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(ValueError, match=rf"config {re.escape(str(bad))}: invalid TOML: .* line 1"):
        load_config(bad)


def test_no_file_points_outside_the_repository():
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
    outside = re.compile(r"\.\./shared|shared/|CONVENTIONS\.md|CONVENTIONS\b")
    hits = []
    for name in tracked:
        path = ROOT / name
        if path.suffix in (".png", ".npz") or not path.is_file():
            continue
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if outside.search(line) and name != "tests/test_packaging.py":
                hits.append(f"{name}:{i}: {line.strip()}")
    assert hits == []


@pytest.mark.parametrize("main", [fit_main, discrepancy_main, convert_main],
                         ids=["fit", "discrepancy", "convert"])
def test_cli_help_names_the_data_format_section_in_plain_text(main, capsys):
    with pytest.raises(SystemExit) as err:
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert err.value.code == 0
    assert 'docs/conventions.md, section "Trajectory file format"' in text
    assert "`" not in text and "CONVENTIONS" not in text
    assert "## Trajectory file format" in (ROOT / "docs" / "conventions.md").read_text()


def test_gait_optimiser_needs_an_output_path(capsys):
    with pytest.raises(SystemExit) as err:
        optimize.main([])
    assert err.value.code == 2
    assert "--out" in capsys.readouterr().err


# ----------------------------------------------------------------------- fresh venv (slow)


def _run(cmd, cwd, env, timeout=900):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


@pytest.mark.slow
def test_wheel_in_a_fresh_venv_runs_every_command_outside_the_checkout(tmp_path):
    """Build the wheel, install it with the constraints into a new venv, and run the three
    console scripts and reference_gait("9link") from a folder that is not the checkout.

    Then the same with an editable install of the sources. About 3-4 minutes on an idle
    machine, most of it pip installing torch and numpy/scipy/matplotlib.
    """
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["OMP_NUM_THREADS"] = "1"
    # build from a copy: a build/ folder left in the checkout could leak stale files
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv*", "build", "dist", "*.egg-info", "runs", "__pycache__", "figures"))
    dist = tmp_path / "dist"
    build = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)]
    try:
        import setuptools  # noqa: F401  # building in this environment skips a download

        build.insert(4, "--no-build-isolation")
    except ImportError:
        pass
    _run(build, tmp_path, env)
    (wheel,) = dist.glob("torchconn-*.whl")

    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    bin_ = env_dir / "bin"
    _run([bin_ / "python", "-m", "pip", "install", "-q", "-c", ROOT / "constraints.txt", wheel],
         tmp_path, env)
    installed = {p for p in (env_dir / "lib").rglob("torchconn/**/*") if p.is_file()}

    work = tmp_path / "elsewhere"
    work.mkdir()
    info = _run([bin_ / "python", "-c", (
        "import json, numpy as np, torch, torchconn\n"
        "from importlib.resources import files\n"
        "from torchconn import NLinkSwimmer, simulate, observe, write_csv\n"
        "from torchconn.physics.gaits import reference_gait\n"
        "g = reference_gait('9link')\n"
        "tr = simulate(NLinkSwimmer(3), reference_gait('3link'), eta=0.025, n_cycles=8,\n"
        "              seeds=np.arange(2))\n"
        "write_csv(observe(tr, 0.002, seeds=np.arange(2)), 'trials.csv')\n"
        "print(json.dumps({'file': torchconn.__file__, 'configs': str(files('torchconn.configs')),\n"
        "                  'version': torchconn.__version__, 'torch': torch.__version__,\n"
        "                  'gait_d': g.shape_dim}))\n"
    )], work, env)
    info = json.loads(info.strip().splitlines()[-1])
    site = str(env_dir)
    assert info["file"].startswith(site) and info["configs"].startswith(site)
    assert info["version"] == PYPROJECT["project"]["version"] and info["gait_d"] == 8
    assert info["torch"].startswith("2.13.0")

    _run([bin_ / "torchconn-sweep", "--config", "quick", "--quiet", "--out", "sweep"], work, env)
    for name in ("results.csv", "claims.csv", "phase_errors.csv", "run.json"):
        assert (work / "sweep" / name).stat().st_size > 0, name
    run = json.loads((work / "sweep" / "run.json").read_text())
    assert run["config"]["name"] == "quick" and run["versions"]["torchconn"] == info["version"]
    _run([bin_ / "torchconn-fit", "trials.csv", "--links", "3", "--out", "fit"], work, env)
    assert (work / "fit" / "model.npz").exists() and (work / "fit" / "connection.csv").exists()
    _run([bin_ / "torchconn-discrepancy", "trials.csv", "--links", "3", "--out", "diag",
          "--quiet", "--no-figures"], work, env)
    assert json.loads((work / "diag" / "report.json").read_text())["verdict"] in (
        "none", "effect", "unexplained")
    # nothing was written into the installed package (the shipped recordings are in it)
    assert {p.name for p in installed} >= {"XMUC02_Trial1_sleap-1.csv", "ATTRIBUTION.md"}
    written = [p for p in (env_dir / "lib").rglob("torchconn/**/*")
               if p.is_file() and p.suffix != ".pyc" and p not in installed]
    assert written == []

    # the same venv, now with an editable install of the sources: configs/ is the package
    _run([bin_ / "python", "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
          "-e", src], tmp_path, env)
    out = _run([bin_ / "python", "-c", (
        "import torchconn; from importlib.resources import files\n"
        "from torchconn.sweep.config import load_config\n"
        "print(torchconn.__file__, files('torchconn.configs'), load_config('fig4a').name)")],
        work, env).split()
    assert out == [str(src / "torchconn" / "__init__.py"), str(src / "configs"), "fig4a"]
