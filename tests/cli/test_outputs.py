"""All-or-nothing outputs of every command: a killed or failed run leaves the previous complete
result or none, one writer per folder, the umask's modes, and no user file ever deleted."""

import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from torchconn import NLinkSwimmer, simulate
from torchconn._output import RECORD, FolderLock, OutputFolder, write_bytes_atomic
from torchconn.convert import main as convert_main
from torchconn.convert import output_names
from torchconn.discrepancy.__main__ import main as discrepancy_main
from torchconn.fit import main as fit_main
from torchconn.fit import write_connection_csv
from torchconn.improve.__main__ import main as improve_main
from torchconn.io.trajectory_files import read_csv, write_csv
from torchconn.physics.gaits import reference_gait
from torchconn.regression.model import LocalConnectionModel
from torchconn.sweep.__main__ import main as sweep_main
from torchconn.sweep.config import load_config
from torchconn.sweep.runner import run_sweep
from torchconn.sweep.store import read_table
from torchconn.testing.tracking import render_keypoints

ROOT = Path(__file__).resolve().parents[2]
PAUSE = "TORCHCONN_TEST_WRITE_PAUSE"
FIT = ["--links", "3", "--no-figures", "--metric", "no"]
TINY = """
name = "tiny"
seed = 11
error_bins = 12
block_trials = 4
simulation = {n_cycles = 5, samples_per_cycle = 32}
estimator = {regression = {n_bins = 16, fourier_order = 4}}
experiment = [{system = "3link", noise_kind = "system", levels = [1.0], trials = 4}]
"""  # one cell


# ============================================================================ helpers
def _recording(path: Path, n_cycles: int) -> Path:
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=n_cycles,
                    samples_per_cycle=32, substeps=4, seeds=[1])
    return write_csv(traj[0], path)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("data")
    _recording(d / "six.csv", 6)  # enough for fit and improve propose
    _recording(d / "twelve.csv", 12)  # the discrepancy workflow needs 10 cycles
    return d


@pytest.fixture(scope="module")
def earlier_fit(data, tmp_path_factory) -> Path:
    """A complete fit, figures included, to be copied and re-fitted over."""
    out = tmp_path_factory.mktemp("earlier") / "fit"
    assert fit_main([str(data / "six.csv"), "--links", "3", "--metric", "no",
                     "--out", str(out)]) == 0
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _snapshot(folder: Path) -> dict[str, bytes] | None:
    """Every file under ``folder`` (hidden ones too) with its bytes; None when it is missing."""
    if not folder.exists():
        return None
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _beside(out: Path) -> list[str]:
    """What lies beside ``out`` that a run on it makes: ``.<name>.lock``, staging folders."""
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


def _error(code: int, err: str, *fragments: str) -> str:
    """The one error line of a clean failure (exit code 2, no traceback)."""
    assert code == 2, err
    assert "Traceback" not in err and "internal error" not in err, err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1, err
    for fragment in fragments:
        assert fragment in errors[0], f"{fragment!r} not in {errors[0]!r}"
    return errors[0]


def _full_disk_at(monkeypatch, name: str) -> None:
    """Make flushing the file ``name`` to disk fail as on a full disk (ENOSPC): the write is
    of the temporary file ``.<name>.XXXXXXXX.tmp``, found through ``/proc/self/fd``."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc/self/fd to find which file a descriptor writes")
    real = os.fsync

    def fsync(fd):
        if Path(os.readlink(f"/proc/self/fd/{fd}")).name.startswith(f".{name}."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


def _must_not_run(*args, **kwargs):
    raise AssertionError("the input was read before the output folder was checked")


def _modes(folder: Path) -> set[int]:
    return {p.stat().st_mode & 0o777 for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def umask():
    """``umask(mask)`` sets the process's umask for the test, restored after it."""
    before = os.umask(0o022)
    os.umask(before)
    yield os.umask
    os.umask(before)


def _env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **extra}


def _kill_when(proc: subprocess.Popen, ready, timeout: float = 300) -> None:
    """SIGKILL ``proc`` as soon as ``ready()`` holds."""
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, "the moment to kill never came"
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def _staged(out: Path) -> list[Path]:
    """Files in the staging folder(s) beside ``out``, temporary ones left out."""
    return [p for d in out.parent.glob(f".{out.name}.staging-*") for p in d.iterdir()
            if p.is_file() and not p.name.endswith(".tmp")]


# ============================================================================ fit
def test_refit_replaces_the_earlier_result_whole(data, earlier_fit, tmp_path):
    out = _copy(earlier_fit, tmp_path / "fit")
    assert (out / "connection.png").exists()
    assert fit_main([str(data / "six.csv"), *FIT, "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert not any(n.endswith(".png") for n in names)  # the earlier fit's plots are gone
    record = json.loads((out / RECORD).read_text())
    assert record["command"] == "torchconn-fit" and set(record["files"]) == names - {RECORD}
    assert {"model.npz", "connection.csv", "fit.json"} <= names
    assert _beside(out) == []


def test_fit_on_a_full_disk_names_the_file_and_keeps_the_earlier_result(data, earlier_fit,
                                                                       tmp_path, capsys,
                                                                       monkeypatch):
    out = _copy(earlier_fit, tmp_path / "fit")
    before = _snapshot(out)
    _full_disk_at(monkeypatch, "connection.csv")  # model.npz is written before it
    code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
    _error(code, capsys.readouterr().err, f"{out / 'connection.csv'}: No space left on device")
    assert _snapshot(out) == before
    assert _beside(out) == []


@pytest.mark.parametrize("name", ["model.npz", "fit.json", RECORD])
def test_fit_on_a_full_disk_leaves_nothing_where_there_was_nothing(name, data, tmp_path,
                                                                   capsys, monkeypatch):
    out = tmp_path / "new" / "deeper" / "fit"  # its parents are made by the run, and unmade
    _full_disk_at(monkeypatch, name)
    code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
    _error(code, capsys.readouterr().err, str(out / name), "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_a_second_writer_is_refused_naming_the_holder(data, earlier_fit, tmp_path, capsys,
                                                      monkeypatch):
    out = _copy(earlier_fit, tmp_path / "fit")
    before = _snapshot(out)
    monkeypatch.setattr("torchconn.fit.read_csv", _must_not_run)

    class Abort(Exception):
        pass

    with pytest.raises(Abort):
        with OutputFolder(out, command="torchconn-fit"):
            code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
            _error(code, capsys.readouterr().err, f"output folder {out} is in use by pid "
                   f"{os.getpid()} on host {socket.gethostname()}", "choose another --out")
            raise Abort  # the holder fails: nothing of it is kept
    assert _snapshot(out) == before
    assert _beside(out) == []


@pytest.mark.parametrize("mask, file_mode, dir_mode", [(0o022, 0o644, 0o755),
                                                       (0o027, 0o640, 0o750)])
def test_outputs_follow_the_umask(mask, file_mode, dir_mode, data, tmp_path, umask):
    umask(mask)
    out = tmp_path / "fit"
    out.mkdir()  # an empty folder (but for the OS's litter) is used as it is
    (out / ".DS_Store").write_bytes(b"")
    assert fit_main([str(data / "six.csv"), *FIT, "--out", str(out)]) == 0
    assert _modes(out) == {file_mode}
    assert out.stat().st_mode & 0o777 == dir_mode
    assert not (out / ".DS_Store").exists()


@pytest.mark.parametrize("kind", ["user files", "an earlier fit and a user file",
                                  "another command's result", "a damaged record", "a file",
                                  "an older torchconn's fit"])
def test_a_folder_that_is_not_an_earlier_fit_is_refused(kind, data, earlier_fit, tmp_path,
                                                        capsys, monkeypatch):
    out = tmp_path / "out"
    if kind == "a file":
        out.write_text("mine")
    elif kind == "an earlier fit and a user file":
        _copy(earlier_fit, out)
        (out / "notes.txt").write_text("mine")
    elif kind == "an older torchconn's fit":
        _copy(earlier_fit, out)
        (out / RECORD).unlink()
    else:
        out.mkdir()
        (out / "notes.txt").write_text("mine")
        if kind == "another command's result":
            (out / RECORD).write_text(json.dumps({"format": "torchconn.output/1",
                                                  "command": "torchconn-convert",
                                                  "files": ["notes.txt"]}))
        elif kind == "a damaged record":
            (out / RECORD).write_text('{"format": "torchconn.out')
    before = _snapshot(out) if out.is_dir() else out.read_bytes()
    monkeypatch.setattr("torchconn.fit.read_csv", _must_not_run)
    code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
    expect = {"user files": "holds no earlier torchconn-fit result",
              "an earlier fit and a user file": "files it did not write (notes.txt)",
              "another command's result": "holds the result of torchconn-convert",
              "a damaged record": "holds no earlier torchconn-fit result",
              "a file": "is a file",
              "an older torchconn's fit": "holds the outputs of an older torchconn"}[kind]
    _error(code, capsys.readouterr().err, f"--out {out}", expect)
    assert (_snapshot(out) if out.is_dir() else out.read_bytes()) == before
    assert _beside(out) == []


def test_a_failed_run_leaves_nothing_behind(tmp_path, capsys):
    out = tmp_path / "a" / "b" / "fit"
    code = fit_main([str(tmp_path / "missing.csv"), *FIT, "--out", str(out)])
    _error(code, capsys.readouterr().err, "missing.csv")
    assert list(tmp_path.iterdir()) == []  # not even the parents it made


def test_the_leftovers_of_a_killed_run_are_cleaned_by_the_next(data, earlier_fit, tmp_path,
                                                               capsys):
    out = _copy(earlier_fit, tmp_path / "fit")
    staging = tmp_path / ".fit.staging-abcd1234"  # as a run killed mid-write leaves them
    staging.mkdir()
    (staging / "model.npz").write_bytes(b"half")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / ".fit.lock").write_text(json.dumps(
        {"pid": dead.pid, "host": socket.gethostname(), "started": "2020-01-01T00:00:00"}))
    (tmp_path / ".other.staging-abcd1234").mkdir()  # another target's: not touched
    assert fit_main([str(data / "six.csv"), *FIT, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"taking over the lock left in {out} by pid {dead.pid}" in err
    assert "no longer running" in err and ".fit.staging-abcd1234" in err
    assert _beside(out) == [] and (tmp_path / ".other.staging-abcd1234").is_dir()
    assert LocalConnectionModel.load(out / "model.npz").batch_shape == ()


def test_an_earlier_result_moved_aside_by_a_killed_run_is_restored(earlier_fit, tmp_path,
                                                                  capsys):
    """Where the folders cannot be exchanged in one step, the earlier result is moved aside
    first: a kill then leaves it beside, and the next run puts it back."""
    before = _snapshot(earlier_fit)
    _copy(earlier_fit, tmp_path / ".fit.old-abcd1234")
    out = tmp_path / "fit"
    code = fit_main([str(tmp_path / "missing.csv"), *FIT, "--out", str(out)])  # fails
    err = capsys.readouterr().err
    _error(code, err, "missing.csv")
    assert "restored the previous result" in err
    assert _snapshot(out) == before
    assert _beside(out) == []


def test_without_an_atomic_exchange_the_swap_still_keeps_the_earlier_result(
        data, earlier_fit, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("torchconn._output._exchange", lambda a, b: False)
    out = _copy(earlier_fit, tmp_path / "fit")
    before = _snapshot(out)
    real = os.rename

    def rename(src, dst):
        if ".staging-" in str(src):
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(src))
        return real(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
    _error(code, capsys.readouterr().err, f"{out}: Input/output error")
    assert _snapshot(out) == before and _beside(out) == []
    monkeypatch.setattr(os, "rename", real)
    assert fit_main([str(data / "six.csv"), *FIT, "--out", str(out)]) == 0
    assert not (out / "connection.png").exists() and _beside(out) == []


def _fit_cmd(data: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "torchconn.fit", str(data / "six.csv"), *FIT, "--out",
            str(out)]


@pytest.mark.parametrize("moment", [
    "before the swap",
    pytest.param("after the first file", marks=pytest.mark.slow),
    pytest.param("no earlier result", marks=pytest.mark.slow),
])
def test_a_fit_killed_while_writing_leaves_the_earlier_result_or_none(moment, data,
                                                                      earlier_fit, tmp_path,
                                                                      capsys):
    out = tmp_path / "fit"
    if moment != "no earlier result":
        _copy(earlier_fit, out)
    before = _snapshot(out)
    # a pause after the first file (model.npz), or after the record, the last before the swap
    last = RECORD if moment == "before the swap" else "model.npz"
    proc = subprocess.Popen(_fit_cmd(data, out), env=_env(**{PAUSE: f"60:{last}"}),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _kill_when(proc, lambda: any(p.name == last for p in _staged(out)))
    assert _snapshot(out) == before
    assert _beside(out)  # the killed run's staging folder and lock
    assert fit_main([str(data / "six.csv"), *FIT, "--out", str(out)]) == 0
    assert "removed the staging folder" in capsys.readouterr().err
    assert _beside(out) == [] and (out / "fit.json").exists()


@pytest.mark.slow  # two processes
def test_two_fits_into_one_folder_at_once(data, tmp_path, capsys):
    out = tmp_path / "fit"
    proc = subprocess.Popen(_fit_cmd(data, out), env=_env(**{PAUSE: "2"}),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not _staged(out):
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    code = fit_main([str(data / "six.csv"), *FIT, "--out", str(out)])
    _error(code, capsys.readouterr().err, f"in use by pid {proc.pid}")
    assert proc.wait(timeout=300) == 0, proc.stderr.read()
    assert OutputFolder.read_record(out)["command"] == "torchconn-fit"


# ============================================================================ convert
@pytest.fixture(scope="module")
def tracks(tmp_path_factory) -> list[Path]:
    """Two point-array tracking files of one name, ``a/fish.npz`` and ``b/fish.npz``."""
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=4,
                    samples_per_cycle=32, substeps=4, seeds=[3, 4])
    kps = render_keypoints(traj, NLinkSwimmer(3), per_link=3, noise_px=0.3, seed=5)
    root = tmp_path_factory.mktemp("tracks")
    paths = []
    for folder, kp in zip("ab", kps, strict=True):
        (root / folder).mkdir()
        paths.append(root / folder / "fish.npz")
        np.savez(paths[-1], points=kp.points, scores=kp.scores, t=kp.times,
                 names=np.array(kp.names))
    return paths


CONVERT = ["--links", "3", "--flip-y", "--curve", "polyline"]


def test_sources_of_one_name_get_distinct_outputs(tracks, tmp_path, umask):
    umask(0o002)
    out = tmp_path / "csv"
    assert convert_main([*map(str, tracks), *CONVERT, "--out", str(out)]) == 0
    sidecar = json.loads((out / "convert.json").read_text())
    made = {f["source"]: f["outputs"] for f in sidecar["files"]}
    assert made == {str(tracks[0]): [str(out / "a_fish.csv")],
                    str(tracks[1]): [str(out / "b_fish.csv")]}
    # each file is its own source's conversion
    alone = tmp_path / "alone"
    assert convert_main([str(tracks[1]), *CONVERT, "--out", str(alone)]) == 0
    assert (alone / "fish.csv").read_bytes() == (out / "b_fish.csv").read_bytes()
    assert (out / "a_fish.csv").read_bytes() != (out / "b_fish.csv").read_bytes()
    assert _modes(out) == {0o664}


def test_output_names_are_distinct_and_deterministic():
    names = output_names([Path("x/a/fish.npz"), Path("y/a/fish.h5"), Path("y/b/Fish.csv"),
                          Path("a_fish.npz"), Path("eel.npz"), Path("eel_trial0.npz")],
                         [1, 2, 1, 1, 2, 1])
    assert names == [["a_fish.csv"], ["a_fish_trial0.csv", "a_fish_trial1.csv"],
                     ["b_Fish.csv"], ["a_fish-2.csv"], ["eel_trial0.csv", "eel_trial1.csv"],
                     ["eel_trial0-2.csv"]]
    flat = [n.casefold() for group in names for n in group]
    assert len(set(flat)) == len(flat)


def test_a_source_given_twice_is_refused(tracks, tmp_path, capsys):
    out = tmp_path / "csv"
    again = tracks[0].parent / ".." / "a" / "fish.npz"
    code = convert_main([str(tracks[0]), str(again), *CONVERT, "--out", str(out)])
    _error(code, capsys.readouterr().err, "inputs 1 and 2 name the same file")
    assert list(tmp_path.iterdir()) == []


def test_convert_on_a_full_disk_writes_nothing(tracks, tmp_path, capsys, monkeypatch):
    out = tmp_path / "csv"
    _full_disk_at(monkeypatch, "b_fish.csv")
    code = convert_main([*map(str, tracks), *CONVERT, "--out", str(out)])
    _error(code, capsys.readouterr().err, f"{out / 'b_fish.csv'}: No space left on device")
    assert list(tmp_path.iterdir()) == []


# ============================================================================ discrepancy
def test_discrepancy_on_a_full_disk_keeps_the_earlier_report(data, tmp_path, capsys,
                                                             monkeypatch):
    out = tmp_path / "d"
    args = [str(data / "twelve.csv"), "--links", "3", "--out", str(out), "--candidates",
            "ambient_flow", "--no-terms", "--no-figures", "--quiet"]
    assert discrepancy_main(args) == 0
    before = _snapshot(out)
    assert {"report.json", "residual_profile.csv", RECORD} <= set(before)
    _full_disk_at(monkeypatch, "residual_profile.csv")  # report.json is written before it
    code = discrepancy_main(args)
    _error(code, capsys.readouterr().err, f"{out / 'residual_profile.csv'}: No space left")
    assert _snapshot(out) == before and _beside(out) == []


# ============================================================================ improve
def test_improve_on_a_full_disk_or_into_a_fit_writes_nothing(data, earlier_fit, tmp_path,
                                                             capsys, monkeypatch):
    fitted = _copy(earlier_fit, tmp_path / "fit")
    before = _snapshot(fitted)
    monkeypatch.setattr("torchconn.improve.__main__.read_csv", _must_not_run)
    code = improve_main(["propose", str(data / "six.csv"), "--links", "3", "--out",
                         str(fitted)])
    _error(code, capsys.readouterr().err, "holds the result of torchconn-fit")
    assert _snapshot(fitted) == before
    monkeypatch.undo()
    out = tmp_path / "next"
    _full_disk_at(monkeypatch, "report.json")  # next_gait.csv and .json are written before
    code = improve_main(["propose", str(data / "six.csv"), "--links", "3", "--out", str(out)])
    _error(code, capsys.readouterr().err, f"{out / 'report.json'}: No space left on device")
    assert not out.exists() and _beside(out) == []


# ============================================================================ sweep
@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


def test_sweep_removes_stale_cells_and_temporary_files_and_says_so(tiny, tmp_path, umask):
    umask(0o027)
    out = tmp_path / "sweep"
    config = load_config(tiny)
    run_sweep(config, out, quiet=True, figures=False)
    (cell,) = (out / "cells").iterdir()
    assert _modes(out) == {0o640}  # the store's tables and records follow the umask too
    # a cell of older code, one of this code but another config, an incomplete one, a
    # folder the store did not make, and the temporary files of a killed run
    old = _copy(cell, out / "cells" / f"{cell.name[:-16]}{'0' * 16}")
    manifest = json.loads((old / "cell.json").read_text())
    (old / "cell.json").write_text(json.dumps({**manifest, "source_hash": "0" * 16}))
    other = _copy(cell, out / "cells" / f"other-L0-t0-4-{'1' * 16}")
    half = _copy(cell, out / "cells" / f"other-L0-t4-8-{'2' * 16}")
    (half / "cell.json").unlink()
    mine = out / "cells" / "notes"
    mine.mkdir()
    temporary = [out / ".results.csv.abcd1234.tmp", cell / ".cell.json.x_y12345.tmp"]
    for p in temporary:
        p.write_bytes(b"half")
    with pytest.warns(UserWarning) as warned:  # even when quiet: files are deleted
        summary = run_sweep(config, out, quiet=True, figures=False)
    err = "\n".join(str(w.message) for w in warned)
    assert summary.computed == ()  # the current cell is reused
    assert dict(summary.removed) == {old.name: "computed by other torchconn code",
                                     half.name: "incomplete or damaged, and not a cell of "
                                                "this run"}
    assert sorted(summary.temporary) == sorted(str(p.relative_to(out)) for p in temporary)
    for name, reason in summary.removed:
        assert f"removing stale cell folder cells/{name}: {reason}" in err
    assert "removed 2 temporary file(s)" in err
    assert not old.exists() and not half.exists() and not any(p.exists() for p in temporary)
    assert other.is_dir() and mine.is_dir() and cell.is_dir()
    run = json.loads((out / "run.json").read_text())
    assert [c["cell"] for c in run["cells_removed_stale"]] == [name for name, _ in
                                                               summary.removed]
    # a changed config supersedes the cell of the same name
    changed = load_config(tiny, ["simulation.n_cycles=6"])
    with pytest.warns(UserWarning, match=f"removing stale cell folder cells/{cell.name}"):
        summary = run_sweep(changed, out, quiet=True, figures=False)
    assert summary.removed == ((cell.name, "superseded: the config now gives this cell "
                                           "another fingerprint"),)
    assert other.is_dir() and mine.is_dir()


def test_sweep_on_a_full_disk_names_the_file_and_leaves_no_completion_record(tiny, tmp_path,
                                                                            capsys,
                                                                            monkeypatch):
    out = tmp_path / "sweep"
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    _full_disk_at(monkeypatch, "claims.csv")  # results.csv is rewritten before it
    code = sweep_main(["--config", str(tiny), "--out", str(out), "--quiet", "--no-figures"])
    _error(code, capsys.readouterr().err, f"{out / 'claims.csv'}: No space left on device")
    assert not (out / "run.json").exists()  # the tables may be of two runs
    with pytest.raises(ValueError, match="has not finished"):
        read_table(out / "results.csv")
    assert not [p for p in out.rglob("*.tmp")]
    monkeypatch.undo()
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    assert read_table(out / "results.csv")


def test_sweep_refuses_a_foreign_folder_and_removes_only_its_own_old_outputs(tiny, tmp_path,
                                                                            capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "results.csv").write_text("mine")
    code = sweep_main(["--config", str(tiny), "--out", str(foreign), "--quiet"])
    _error(code, capsys.readouterr().err, f"--out {foreign}", "holds no sweep")
    assert [p.name for p in foreign.iterdir()] == ["results.csv"]
    out = tmp_path / "sweep"
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    # as if the run before had written a figure that this one (--no-figures) does not
    run = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**run, "outputs": run["outputs"] + [
        "fig3b_traces.png"]}))
    (out / "fig3b_traces.png").write_bytes(b"old")
    (out / "notes.txt").write_text("mine")
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    assert not (out / "fig3b_traces.png").exists() and (out / "notes.txt").exists()


@pytest.mark.slow  # a sweep in a subprocess
def test_a_sweep_killed_while_assembling_leaves_no_completion_record(tiny, tmp_path):
    out = tmp_path / "sweep"
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    proc = subprocess.Popen([sys.executable, "-m", "torchconn.sweep", "--config", str(tiny),
                             "--out", str(out), "--quiet", "--no-figures"],
                            env=_env(**{PAUSE: "60:results.csv"}), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    # the stored cell is reused: results.csv is the first file written, run.json gone before
    _kill_when(proc, lambda: not (out / "run.json").exists())
    with pytest.raises(ValueError, match="has not finished"):
        read_table(out / "results.csv")
    assert sweep_main(["--config", str(tiny), "--out", str(out), "--quiet",
                       "--no-figures"]) == 0
    assert read_table(out / "claims.csv")


# ============================================================================ the Python API
def test_api_writers_are_atomic_and_name_the_file(data, earlier_fit, tmp_path, monkeypatch,
                                                  umask):
    umask(0o022)
    model = LocalConnectionModel.load(earlier_fit / "model.npz")
    traj = read_csv(data / "six.csv", n_joints=2)
    writers = {"model.npz": lambda p: model.save(p), "trial.csv": lambda p: write_csv(traj, p),
               "connection.csv": lambda p: write_connection_csv(model, p, 10)}
    for name, write in writers.items():
        path = write(tmp_path / name)
        assert path == tmp_path / name and path.stat().st_mode & 0o777 == 0o644
        before = path.read_bytes()
        with monkeypatch.context() as m:
            _full_disk_at(m, name)
            with pytest.raises(OSError, match="No space left") as info:
                write(path)
        assert info.value.filename == str(path) and path.read_bytes() == before
        folder = tmp_path / f"{name}.d" / name  # a folder where the file should be
        folder.mkdir(parents=True)
        with pytest.raises(IsADirectoryError) as info:
            write(folder)
        assert info.value.filename == str(folder)
    assert model.save(tmp_path / "bare") == tmp_path / "bare.npz"  # as numpy.savez names it
    assert not list(tmp_path.rglob("*.tmp"))


def test_lock_files_beside_a_folder_are_removed_on_release(tmp_path):
    lock = tmp_path / ".out.lock"
    with FolderLock(tmp_path / "out", lock_file=lock, remove=True):
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not lock.exists()
    write_bytes_atomic(tmp_path / "x", b"1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x"]
