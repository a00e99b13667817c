"""``python -m torchconn.improve`` on bad input: every flag's range is checked before the loop
simulates or reads anything (the work is replaced by a stand-in that fails the test), with a
message naming the flag; the settings objects of the Python API check theirs."""

from __future__ import annotations

import math

import pytest

from torchconn.improve import __main__ as improve_cli
from torchconn.improve.loop import LoopSettings
from torchconn.improve.propose import TrustRegion

from .common import assert_clean_failure, must_not_run, write

SIMULATE_CASES = [
    (["--omega", "-0.1"], ["--omega must be >= 0", "-0.1"]),
    (["--omega", "nan"], ["--omega must be a finite number"]),
    (["--radius", "100"], ["--radius must be < π", "joints' amplitude in rad"]),
    (["--radius", "0"], ["--radius must be > 0"]),
    (["--radius", "inf"], ["--radius must be a finite number"]),
    (["--rounds", "0"], ["--rounds must be >= 1"]),
    (["--rounds", "-1"], ["--rounds must be >= 1"]),
    (["--trials", "0"], ["--trials must be >= 1"]),
    (["--cycles", "2"], ["--cycles must be >= 3"]),
    (["--seed", "-1"], ["--seed must be >= 0"]),
    (["--scale", "0"], ["--scale must be > 0"]),
    (["--scale", "inf"], ["--scale must be a finite number"]),
    (["--scale", "10"], ["--scale must lie in [0.5, 4.5]"]),
    (["--links", "2"], ["--links must be >= 3"]),
    (["--device", "tpu"], ["--device 'tpu'", "unknown device"]),
    (["--threads", "0"], ["--threads must be an integer >= 1"]),
]


@pytest.mark.parametrize("argv,fragments", SIMULATE_CASES,
                         ids=[" ".join(c[0]) for c in SIMULATE_CASES])
def test_improve_simulate_flags_checked_before_work(argv, fragments, tmp_path, capsys,
                                                    monkeypatch):
    monkeypatch.setattr("torchconn.improve.__main__.improve", must_not_run)
    out = tmp_path / "o"
    code = improve_cli.main(["simulate", "--out", str(out), *argv])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)
    assert not out.exists()


@pytest.mark.parametrize("name,argv,fragments", [
    ("missing", ["{tmp}/nope.csv", "--links", "3"], ["nope.csv", "not found"]),
    ("empty", ["{tmp}/empty.csv", "--links", "3"], ["empty.csv", "empty"]),
    ("folder", ["{tmp}", "--links", "3"], ["is a folder"]),
    ("wrong-links", ["{rec}", "--links", "5"], ["expected n_joints=4", "--links 5"]),
    ("twice", ["{rec}", "{rec}", "--links", "3"], ["inputs 1 and 2 name the same file"]),
    ("scale-0", ["{rec}", "--links", "3", "--scale", "0"], ["--scale must be > 0"]),
    ("links-2", ["{rec}", "--links", "2"], ["--links must be >= 3"]),
    ("earlier-missing", ["{rec}", "--links", "3", "--earlier", "{tmp}/gone.csv"],
     ["gone.csv", "not found"]),
    ("pool-length-0", ["{rec}", "--links", "3", "--earlier", "{rec}", "--pool-length", "0"],
     ["--pool-length must be > 0"]),
    ("earlier-efficiency", ["{rec}", "--links", "3", "--earlier", "{rec}", "--objective",
                            "efficiency"], ["--objective efficiency needs the metric",
                                            "--earlier"]),
])
def test_improve_propose_bad_input(name, argv, fragments, recording, tmp_path, capsys,
                                   monkeypatch):
    monkeypatch.setattr("torchconn.improve.__main__.propose_gait", must_not_run)
    write(tmp_path, "empty.csv", "")
    out = tmp_path / "o"
    args = [a.format(tmp=tmp_path, rec=recording) for a in argv]
    code = improve_cli.main(["propose", *args, "--out", str(out)])
    assert_clean_failure(code, capsys.readouterr().err, fragments, out)


@pytest.mark.parametrize("cls,kwargs,match", [
    (LoopSettings, dict(omega=-1.0), r"LoopSettings\.omega must be >= 0"),
    (LoopSettings, dict(eta=math.nan), r"LoopSettings\.eta must be a finite number"),
    (LoopSettings, dict(alpha=0.0), r"LoopSettings\.alpha must be > 0"),
    (LoopSettings, dict(level=1.0), r"LoopSettings\.level must be < 1"),
    (LoopSettings, dict(seed=-2), r"LoopSettings\.seed must be >= 0"),
    (LoopSettings, dict(objective="speed"), r"LoopSettings\.objective must be one of"),
    (LoopSettings, dict(poor_ratio=0.9, good_ratio=0.5), r"poor_ratio .* must be <= good_ratio"),
    (LoopSettings, dict(cycles=2), r"LoopSettings\.cycles must be at least 3 \(two whole"),
    (LoopSettings, dict(objective="efficiency"), r"'efficiency' needs the metric"),
    (LoopSettings, dict(pool_length=0.0), r"LoopSettings\.pool_length must be > 0"),
    (LoopSettings, dict(excitation=2.0), r"LoopSettings\.excitation must be <= 1"),
    (TrustRegion, dict(scale=math.inf), r"TrustRegion\.scale must be a finite number"),
    (TrustRegion, dict(lr=0.0), r"TrustRegion\.lr must be > 0"),
    (TrustRegion, dict(steps=0), r"TrustRegion\.steps must be >= 1"),
], ids=["omega", "eta-nan", "alpha-0", "level-1", "seed", "objective", "ratios", "cycles-2",
        "efficiency", "pool-length-0", "excitation-2", "scale-inf", "lr-0", "steps-0"])
def test_improve_settings_api(cls, kwargs, match):
    with pytest.raises(ValueError, match=match):
        cls(**kwargs)
