"""The movement package's datasets and files convert to the same trajectories as the native
readers (needs the extra ``torchconn[movement]``; skipped without it)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchconn import Trajectory
from torchconn.convert import main as convert_main
from torchconn.datasets import prickleback
from torchconn.io.tracking import (
    ConversionSettings,
    TrackingFormatError,
    convert_file,
    detect_format,
    read_tracking,
)
from torchconn.io.trajectory_files import read_csv

movement_io = pytest.importorskip("movement.io")
pytest.importorskip("h5py")
from movement.io import load_dataset, load_poses, save_poses  # noqa: E402

SAMPLES = Path(__file__).resolve().parents[1] / "data" / "tracking"


def same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal values, NaN where the other is NaN (missing frames)."""
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())


def assert_same_trajectory(a: Trajectory, b: Trajectory) -> None:
    assert a.r.shape == b.r.shape
    assert torch.equal(a.t, b.t)
    assert same(a.pose, b.pose) and same(a.r, b.r)


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the samples' few keypoints for their links
        return fn(*args, **kwargs)


@pytest.mark.parametrize("name,track", [("sleap.analysis.h5", None), ("dlc.csv", None),
                                        ("dlc_table.h5", None), ("dlc_fixed.h5", None),
                                        ("dlc_multi.csv", "fish2")])
def test_movement_datasets_of_the_samples_convert_as_the_native_readers(name, track):
    settings = ConversionSettings(n_links=3, fps=25, track=track)
    native = quiet(convert_file, SAMPLES / name, settings).trajectory
    ds = quiet(load_dataset, SAMPLES / name)
    via = quiet(Trajectory.from_movement, ds, 3, fps=25, track=track)
    assert_same_trajectory(via, native)
    assert via.r.isnan().any()  # the samples' lost tail point: a missing frame, in both
    report = via.meta["conversion"]
    assert report["format"] == ("sleap" if name.startswith("sleap") else "dlc")
    # DeepLabCut's likelihood threshold applies to DeepLabCut data from movement too
    assert report["settings"]["min_score"] == (None if name.startswith("sleap") else 0.6)
    # the same file through `--format movement` (movement's loader, the native converter)
    assert_same_trajectory(quiet(convert_file, SAMPLES / name, settings,
                                 format="movement").trajectory, native)


def _prickleback_dataset():
    """The shipped prickleback as a movement dataset at 60 fps (SLEAP stores float32)."""
    kp = read_tracking(prickleback().path)
    return load_poses.from_numpy(
        kp.points.transpose(0, 2, 1)[..., None].astype(np.float32),
        kp.scores[..., None].astype(np.float32), keypoint_names=list(kp.names),
        individual_names=["fish"], fps=60, source_software="SLEAP")


def test_the_prickleback_through_movement_equals_the_native_conversion(tmp_path):
    rec = prickleback()
    native = quiet(rec.convert).trajectory
    ds = _prickleback_dataset()
    # the SLEAP values are float32: movement's float32 arrays hold them exactly
    settings = {f: getattr(rec.settings, f) for f in ("keypoints", "frame", "curve")}
    assert_same_trajectory(quiet(Trajectory.from_movement, ds, 5, **settings), native)
    # written as SLEAP's analysis HDF5 and read back by movement (fps given: frames)
    h5 = tmp_path / "prickleback.analysis.h5"
    save_poses.to_sleap_analysis_file(ds, h5)
    back = quiet(load_dataset, h5)
    assert back.attrs["time_unit"] == "frames"
    assert_same_trajectory(quiet(Trajectory.from_movement, back, 5, fps=60, **settings), native)


def test_untracked_frames_are_dropped_as_the_native_reader_drops_them(tmp_path):
    """Frames without any keypoint (SLEAP's analysis HDF5 lists every video frame) are not
    read: the time origin is the first tracked frame, through movement and natively."""
    ds = _prickleback_dataset()
    ds["position"][:7] = np.nan  # the animal enters at frame 7
    ds["position"][300:305] = np.nan
    h5 = tmp_path / "late.analysis.h5"
    save_poses.to_sleap_analysis_file(ds, h5)
    settings = ConversionSettings(n_links=5, fps=60, time_origin="first")
    native = quiet(convert_file, h5, settings)
    via = quiet(Trajectory.from_movement, quiet(load_dataset, h5), 5, fps=60)
    assert_same_trajectory(via, native.trajectory)
    assert native.report.frames[0] == 7 and via.meta["conversion"]["frames"][0] == 7
    assert float(via.t[0]) == 0.0 and via.r[0, 293:298].isnan().all()


def test_convert_reads_a_file_only_movement_knows(tmp_path):
    """NWB (ndx-pose) is detected as a movement file and converted like the SLEAP CSV."""
    pynwb = pytest.importorskip("pynwb")
    nwb = tmp_path / "prickleback.nwb"
    with pynwb.NWBHDF5IO(nwb, "w") as io:
        io.write(save_poses.to_nwb_file(_prickleback_dataset()))
    assert detect_format(nwb) == "movement"
    rec = prickleback()
    flags = rec.convert_args()[1:]
    assert quiet(convert_main, [str(nwb), *flags, "--out", str(tmp_path / "nwb"), "--quiet"]) == 0
    assert quiet(convert_main, [*rec.convert_args(), "--out", str(tmp_path / "csv"),
                                "--quiet"]) == 0
    a = read_csv(tmp_path / "nwb" / "prickleback.csv", n_joints=4)
    b = read_csv(tmp_path / "csv" / "XMUC02_Trial1_sleap-1.csv", n_joints=4)
    assert_same_trajectory(a, b)


def test_bad_movement_datasets_are_named_errors():
    with pytest.raises(TypeError, match="movement poses dataset"):
        Trajectory.from_movement({"position": 1}, 3)
    ds = _prickleback_dataset()
    ds3 = load_poses.from_numpy(np.zeros((4, 3, 2, 1)), fps=10)  # (time, x y z, keypoints, ind)
    with pytest.raises(TrackingFormatError, match=r"planar poses .* ds.sel\(space=\['x', 'y'\]\)"):
        Trajectory.from_movement(ds3, 3)
    with pytest.raises(TrackingFormatError, match=r"no individual 'eel'; the file has 'fish'"):
        Trajectory.from_movement(ds, 5, track="eel")
    with pytest.raises(TrackingFormatError, match="keypoint\\(s\\) 'head' not in the file"):
        Trajectory.from_movement(ds, 5, keypoints=["head", "Tail"])
