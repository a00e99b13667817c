"""The recordings that ship with torchconn: readable package data with their attribution, and
converted by torchconn-convert with the settings they come with."""

from __future__ import annotations

import importlib.util
import json
import warnings

import pytest
import torch

from torchconn.convert import main as convert_main
from torchconn.datasets import attribution, prickleback
from torchconn.io.tracking import TrackingFormatError, detect_format, read_tracking
from torchconn.io.tracking.readers import MissingDependencyError
from torchconn.io.trajectory_files import read_csv


def test_the_prickleback_is_a_readable_sleap_file_with_its_attribution():
    rec = prickleback()
    assert rec.path.is_file() and rec.path.stat().st_size < 1_000_000
    assert detect_format(rec.path) == "sleap"
    kp = read_tracking(rec.path)
    assert kp.n_frames == 711 and kp.names == rec.settings.keypoints
    assert (rec.settings.n_links, rec.settings.fps) == (5, 60.0)
    text = attribution()
    for needed in ("XMUC02_Trial1_sleap-1.csv", "Tytell", "https://github.com/tytell/fishmechr",
                   "CC BY 4.0", "Changes: none"):
        assert needed in text


def test_convert_on_the_prickleback_with_its_flags(tmp_path, capsys):
    rec = prickleback()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        conversion = rec.convert()
        code = convert_main([*rec.convert_args(), "--out", str(tmp_path / "out")])
    assert code == 0
    traj = conversion.trajectory
    assert traj.r.shape[-1] == 4 and traj.dt == pytest.approx(1 / 60)
    assert conversion.report.n_valid == 711
    written = read_csv(tmp_path / "out" / "XMUC02_Trial1_sleap-1.csv", n_joints=4)
    # the CSV holds what the API converts (to the CSV's printed precision)
    torch.testing.assert_close(written.r, traj.r, rtol=0, atol=1e-9)
    sidecar = json.loads((tmp_path / "out" / "convert.json").read_text())
    assert sidecar["settings"]["keypoints"] == list(rec.settings.keypoints)
    assert "711/711 frames" in capsys.readouterr().out


@pytest.mark.skipif(importlib.util.find_spec("movement") is not None,
                    reason="movement is installed (tests/io/test_movement.py)")
def test_without_movement_the_messages_say_how_to_get_it(tmp_path):
    slp = tmp_path / "fish.slp"
    slp.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    with pytest.raises(TrackingFormatError, match=r"pip install 'torchconn\[movement\]'"):
        detect_format(slp)
    with pytest.raises(MissingDependencyError, match=r"pip install 'torchconn\[movement\]'"):
        read_tracking(prickleback().path, "movement")
