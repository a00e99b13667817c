"""``python -m torchconn.datasets NAME --out DIR``: the shipped recording copied out byte for
byte with its attribution, and bad input answered in one line."""

from __future__ import annotations

import shlex

import pytest

from torchconn.datasets import attribution, prickleback
from torchconn.datasets.__main__ import main


def test_copies_the_recording_and_its_attribution_and_prints_the_convert_command(tmp_path, capsys):
    out = tmp_path / "fish"
    assert main(["prickleback", "--out", str(out)]) == 0
    rec = prickleback()
    copy = out / rec.path.name
    assert copy.read_bytes() == rec.path.read_bytes()
    assert (out / "ATTRIBUTION.md").read_text(encoding="utf-8") == attribution()
    printed = capsys.readouterr().out.splitlines()
    command = shlex.split(printed[-1])
    assert command[:2] == ["torchconn-convert", str(copy)]
    assert command[2:-2] == rec.convert_args()[1:]          # the recording's own flags
    assert command[-2] == "--out"


def test_list_names_every_recording(capsys):
    assert main(["--list"]) == 0
    assert capsys.readouterr().out.startswith("prickleback: rock prickleback")


@pytest.mark.parametrize("argv, message", [
    (["salmon", "--out", "x"], "unknown recording 'salmon'; the recordings are prickleback"),
    (["prickleback"], "--out DIR is required"),
    ([], "name a recording (prickleback), or pass --list"),
])
def test_bad_input_is_one_line_and_exit_code_2(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
    assert not (tmp_path / "x").exists()


def test_an_out_that_is_a_file_is_refused(tmp_path, capsys):
    blocker = tmp_path / "fish"
    blocker.write_text("")
    assert main(["prickleback", "--out", str(blocker)]) == 2
    err = capsys.readouterr().err
    assert f"--out {blocker}: is a file" in err
