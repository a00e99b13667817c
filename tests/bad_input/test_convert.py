"""``torchconn-convert`` on bad input: flags, configs and tracking files. Refused inputs give
exit code 2 and one message naming file, line, column, key or flag, before any work where they
can; doubtful ones (too few keypoints, a threshold without scores, copies) a warning; other
layouts of a tracking CSV (tabs, semicolons with decimal commas, comments, a byte-order mark)
convert to the same trajectory."""

from __future__ import annotations

import gzip
import os

import numpy as np
import pytest

from torchconn.convert import main as convert_main
from torchconn.physics.gaits import reference_gait
from torchconn.physics.systems import NLinkSwimmer
from torchconn.simulation.rollout import simulate
from torchconn.testing.tracking import render_keypoints, write_sleap_csv

from .common import assert_clean_failure, assert_warned, lines, must_not_run, write


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A SLEAP analysis CSV of a simulated 3-link swimmer (7 keypoints, 8 cycles at 5 fps) and
    its points as an NPZ without scores."""
    swimmer = NLinkSwimmer(3)
    traj = simulate(swimmer, reference_gait("3link"), eta=0.025, n_cycles=8,
                    samples_per_cycle=32, substeps=4, seeds=[1])
    kp = render_keypoints(traj[0], swimmer, per_link=2)[0]
    root = tmp_path_factory.mktemp("tracked")
    np.savez(root / "points.npz", points=kp.points)
    return write_sleap_csv(kp, root / "fish.csv"), root / "points.npz"


def _run(argv, tmp_path):
    out = tmp_path / "out"
    return convert_main([*map(str, argv), "--links", "3", "--out", str(out)]), out


@pytest.mark.parametrize("argv,fragments", [
    (["--fps", "0"], ["--fps must be a positive number", "0"]),
    (["--fps", "nan"], ["--fps must be a positive number", "nan"]),
    (["--scale", "-1"], ["--scale must be a positive number"]),
    (["--max-gap", "-1"], ["--max-gap must be a positive number"]),
    (["--min-score", "nan"], ["--min-score must be a finite number"]),
    (["--keypoints", "head"], ["--keypoints must name at least 2 points"]),
    (["--links", "1"], ["--links must be >= 2"]),
    (["--links", "4"], ["--links 4", "odd number of links", "--frame com-mean"]),
    (["--threads", "0"], ["--threads must be an integer >= 1"]),
    (["--set", "convert.curve=zigzag"], ["[convert] curve must be one of", "'zigzag'"]),
    (["--set", "convert.fpss=5"], ["[convert]", "unknown key 'fpss'", "did you mean 'fps'"]),
    (["--set", "estimator.n_bins=3"], ["unknown config section", "estimator"]),
], ids=["fps-0", "fps-nan", "scale", "max-gap", "min-score", "one-keypoint", "links-1",
        "links-even", "threads", "set-value", "set-typo", "set-section"])
def test_convert_flags_checked_before_work(argv, fragments, tracked, tmp_path, capsys,
                                           monkeypatch):
    monkeypatch.setattr("torchconn.cli.conversion.convert_file", must_not_run)
    out = tmp_path / "out"
    links = [] if "--links" in argv else ["--links", "3"]
    code = convert_main([str(tracked[0]), *links, "--out", str(out), "--fps", "5", *argv]
                        if "--fps" not in argv else [str(tracked[0]), *links, "--out", str(out),
                                                     *argv])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)
    assert not out.exists()


@pytest.mark.parametrize("kind,text,fragments", [
    ("folder", None, ["--config", "is a folder"]),
    ("wrong-type", "[convert]\nfps = 'fast'\n", ["[convert] fps", "'fast'"]),
    ("not-a-table", "convert = 3\n", ["[convert] must be a table"]),
    ("syntax", "[convert\n", ["invalid TOML", "line 1"]),
], ids=["folder", "wrong-type", "not-a-table", "syntax"])
def test_convert_config(kind, text, fragments, tracked, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("torchconn.cli.conversion.convert_file", must_not_run)
    path = tmp_path / "c.toml"
    if text is None:
        path.mkdir()
    else:
        write(tmp_path, "c.toml", text)
    code, out = _run([tracked[0], "--fps", "5", "--config", path], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def _mutated(fn):
    def build(fish, tmp):
        return write(tmp, "bad.csv", fn(fish.read_text()))
    return build


def _row(text: str, k: int, fn) -> str:
    rows = text.splitlines()
    rows[k] = fn(rows[k])
    return "\n".join(rows) + "\n"


# (id, builder(fish.csv, tmp_path) -> path(s), fragments)
FILE_CASES = [
    ("gzip", lambda f, tmp: write(tmp, "g.csv", gzip.compress(f.read_bytes())),
     ["g.csv", "gzip-compressed"]),
    ("npz-garbage", lambda f, tmp: write(tmp, "x.npz", b"garbage"),
     ["x.npz", "not an NPZ file"]),
    ("npy-as-npz", lambda f, tmp: (np.save(tmp / "a.npy", np.zeros(3)),
                                   os.replace(tmp / "a.npy", tmp / "a.npz"), tmp / "a.npz")[2],
     ["a.npz", "not an NPZ file", "NumPy .npy array"]),
    ("h5-garbage", lambda f, tmp: write(tmp, "x.h5", os.urandom(300)),
     ["x.h5", "HDF5"]),
    ("wcon-garbage", lambda f, tmp: write(tmp, "x.wcon", "{not json"), ["x.wcon", "JSON"]),
    ("folder", lambda f, tmp: tmp, ["is a folder"]),
    ("missing", lambda f, tmp: tmp / "nope.csv", ["nope.csv", "not found"]),
    ("empty", lambda f, tmp: write(tmp, "e.csv", ""), ["e.csv", "empty"]),
    ("header-only", _mutated(lambda t: t.splitlines()[0] + "\n"), ["bad.csv", "no data rows"]),
    ("ragged-row", _mutated(lambda t: _row(t, 5, lambda r: r + ",1")),
     ["bad.csv", "line 6", "fields, but the header has"]),
    ("text-cell", _mutated(lambda t: _row(t, 5, lambda r: ",".join(
        c if i != 3 else "abc" for i, c in enumerate(r.split(","))))),
     ["bad.csv", "line 6", "column 'head.x'", "non-numeric value 'abc'"]),
    ("decimal-comma-with-commas", _mutated(lambda t: _row(t, 3, lambda r: r.replace(".", ","))),
     ["bad.csv", "line 4", "decimal commas"]),
    ("frame-twice", _mutated(lambda t: _row(t, 5, lambda r: ",".join(
        c if i != 1 else "3" for i, c in enumerate(r.split(","))))),
     ["bad.csv", "frame 3"]),
    ("latin-1", lambda f, tmp: write(tmp, "l.csv", ("# caf\u00e9\n" + f.read_text())
                                     .encode("latin-1")), ["l.csv", "line 1", "not UTF-8"]),
    ("dlc-truncated", lambda f, tmp: write(tmp, "dlc.csv",
                                           "scorer,DLC,DLC\nbodyparts,head,head\n"),
     ["dlc.csv", "DeepLabCut"]),
]


@pytest.mark.parametrize("case", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_convert_bad_files(case, tracked, tmp_path, capsys):
    _, build, fragments = case
    path = build(tracked[0], tmp_path)
    code, out = _run([path, "--fps", "5"], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


def test_convert_same_file_twice_and_trajectory_csvs(tracked, recording, tmp_path, capsys):
    code, out = _run([tracked[0], tracked[0], "--fps", "5"], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, ["inputs 1 and 2 name the same file"],
                         out)
    code, out = _run([recording], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, ["already trajectory CSVs"], out)
    code, out = _run([tracked[0], recording, "--fps", "5"], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, ["mixed with tracking files"], out)


@pytest.mark.parametrize("argv,fragments", [
    (["--links", "9"], ["7 keypoints for 9 links", "interpolated, not tracked"]),
    (["--min-score", "0.5", "NPZ"], ["min_score 0.5 has no effect", "no confidence scores"]),
    (["COPY"], ["identical contents"]),
], ids=["few-keypoints", "min-score-without-scores", "copies"])
def test_convert_doubtful_inputs_are_warned_of(argv, fragments, tracked, tmp_path, capsys):
    source = tracked[1] if "NPZ" in argv else tracked[0]
    extra = [a for a in argv if a not in ("NPZ", "COPY")]
    files = [source] + ([write(tmp_path, "copy.csv", source.read_bytes())]
                        if "COPY" in argv else [])
    links = [] if "--links" in extra else ["--links", "3"]
    code = convert_main([*map(str, files), *links, "--out", str(tmp_path / "out"), "--fps",
                         "5", *extra])
    assert_warned(code, capsys.readouterr().err, fragments)


@pytest.mark.parametrize("name", ["tabs", "semicolons-decimal-comma", "comments", "bom",
                                  "quoted-header", "crlf"])
def test_convert_reads_other_layouts_to_the_same_trajectory(name, tracked, tmp_path, capsys):
    text = tracked[0].read_text()
    rows = text.splitlines()
    variant = {
        "tabs": text.replace(",", "\t"),
        "semicolons-decimal-comma": "\n".join([rows[0].replace(",", ";")] + [
            r.replace(",", ";").replace(".", ",") for r in rows[1:]]) + "\n",
        "comments": "# exported by SLEAP\n" + text,
        "bom": b"\xef\xbb\xbf" + text.encode(),
        "quoted-header": ",".join(f'"{h}"' for h in rows[0].split(",")) + "\n"
                         + "\n".join(rows[1:]) + "\n",
        "crlf": text.replace("\n", "\r\n"),
    }[name]
    assert convert_main([str(tracked[0]), "--links", "3", "--out", str(tmp_path / "plain"),
                         "--fps", "5"]) == 0
    path = write(tmp_path, "fish.csv", variant)
    assert convert_main([str(path), "--links", "3", "--out", str(tmp_path / "other"),
                         "--fps", "5"]) == 0
    assert str(path) not in capsys.readouterr().err
    assert lines(tmp_path / "other" / "fish.csv") == lines(tmp_path / "plain" / "fish.csv")


@pytest.mark.parametrize("track", ["-1", "fish"])
def test_convert_refuses_a_track_for_a_point_array(track, tracked, tmp_path, capsys):
    code, out = _run([tracked[1], "--fps", "5", "--track", track], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err,
                         [str(tracked[1]), "holds one animal", f"track '{track}' (--track)"], out)


def test_convert_refuses_an_unknown_track(tracked, tmp_path, capsys):
    code, out = _run([tracked[0], "--fps", "5", "--track", "shark"], tmp_path)
    assert_clean_failure(code, capsys.readouterr().err, [str(tracked[0]), "'shark'"], out)
