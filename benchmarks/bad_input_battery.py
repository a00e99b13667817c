"""A battery of bad inputs and faults for every command, judged as a user would.

Each case runs one command in-process (``main(argv)``) on files made here: a good simulated
recording and its mutations (encodings, dialects, units, gaps, lengths, values), bad flags and
configs. A case is judged by:

- ``traceback``: exit code 1 (an internal error) or a Python traceback in the output;
- ``silent``: exit code 0 where the case is one that must be refused or warned of, with no
  ``warning`` in the output;
- ``partial``: a failed run that left an output folder it did not find, or changed one it did;
- ``ok``: anything else. Every message is written to ``--log`` for reading.

Run by hand (one thread; a few minutes)::

    python benchmarks/bad_input_battery.py --log /tmp/battery.txt
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import hashlib
import io
import os
import shutil
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from accuracy import circle_gait  # beside this file

from torchconn import NLinkSwimmer, simulate
from torchconn.io.trajectory_files import write_csv
from torchconn.physics.gaits import reference_gait
from torchconn.simulation.observe import observe


@dataclass
class Case:
    name: str
    command: str  # fit, convert, discrepancy, improve, sweep
    argv: list[str]
    must_flag: bool = True  # exit 0 without a warning is a silent wrong answer
    out: Path | None = None
    files: dict = field(default_factory=dict)


def _main(command: str):
    if command == "fit":
        from torchconn.fit import main
    elif command == "convert":
        from torchconn.convert import main
    elif command == "discrepancy":
        from torchconn.discrepancy.__main__ import main
    elif command == "improve":
        from torchconn.improve.__main__ import main
    else:
        from torchconn.sweep.__main__ import main
    return main


def _snapshot(path: Path) -> dict | None:
    if not path.exists():
        return None
    if path.is_file():
        return {"": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): (hashlib.sha256(p.read_bytes()).hexdigest()
                                       if p.is_file() else "dir")
            for p in sorted(path.rglob("*")) if not p.name.startswith(".lock")}


def run_case(case: Case) -> tuple[str, int, str]:
    before = _snapshot(case.out) if case.out else None
    siblings = set(case.out.parent.iterdir()) if case.out and case.out.parent.exists() else set()
    buf_out, buf_err = io.StringIO(), io.StringIO()
    code = None
    with contextlib.redirect_stdout(buf_out), contextlib.redirect_stderr(buf_err), \
            warnings.catch_warnings():
        warnings.simplefilter("always")
        try:
            code = _main(case.command)(case.argv)
        except SystemExit as e:  # argparse
            code = e.code if isinstance(e.code, int) else 2
        except BaseException as e:  # noqa: BLE001 - a raw exception is what is judged
            import traceback

            traceback.print_exc(file=buf_err)
            code = f"raised {type(e).__name__}"
    text = buf_out.getvalue() + buf_err.getvalue()
    if code == 1 or not isinstance(code, int) or "Traceback (most recent call last)" in text:
        verdict = "traceback"
    elif code == 0 and case.must_flag and "warning" not in text.lower():
        verdict = "silent"
    else:
        verdict = "ok"
    if verdict == "ok" and code != 0 and case.out is not None:
        after = _snapshot(case.out)
        leftovers = {p for p in case.out.parent.iterdir() if p not in siblings
                     and p != case.out and not p.name.endswith(".lock")}
        if after != before or leftovers:
            verdict = "partial"
    return verdict, code, text


def build_cases(root: Path) -> list[Case]:
    swimmer = NLinkSwimmer(3)
    seeds = np.array([1, 2])
    traj = simulate(swimmer, reference_gait("3link"), eta=0.025, n_cycles=10,
                    samples_per_cycle=32, seeds=seeds)
    traj = observe(traj, 0.002, seeds=seeds)
    good = root / "good.csv"
    write_csv(traj, good)
    lines = good.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    cols = header.split(",")
    table = np.array([[float(v) if v else np.nan for v in r.split(",")] for r in rows])

    def csv_from(name: str, text: str | bytes) -> Path:
        p = root / name
        (p.write_bytes if isinstance(text, bytes) else p.write_text)(text)
        return p

    def table_csv(name: str, tab: np.ndarray, head=cols) -> Path:
        body = "\n".join(",".join("" if np.isnan(v) else repr(float(v)) if head[j] != "trial"
                                  else str(int(v)) for j, v in enumerate(r)) for r in tab)
        return csv_from(name, ",".join(head) + "\n" + body + "\n")

    c = {n: i for i, n in enumerate(cols)}
    rcols = [c[k] for k in cols if k.startswith("r")]
    cases: list[Case] = []
    k = [0]

    def fit(name, files, *extra, must_flag=True, links="3"):
        k[0] += 1
        out = root / f"out{k[0]}"
        argv = [str(f) for f in files] + ["--out", str(out), "--no-figures", *extra]
        if links is not None:
            argv += ["--links", links]
        cases.append(Case(name, "fit", argv, must_flag, out))

    # --- file-level faults
    fit("missing file", [root / "nope.csv"])
    fit("a folder as data", [root])
    fit("empty file", [csv_from("empty.csv", "")])
    fit("header only", [csv_from("header.csv", header + "\n")])
    fit("one row", [csv_from("one.csv", header + "\n" + rows[0] + "\n")])
    fit("binary garbage", [csv_from("garbage.csv", os.urandom(4000))])
    fit("gzip file", [csv_from("gz.csv", gzip.compress(good.read_bytes()))])
    fit("latin-1 header", [csv_from("latin.csv", ("t,x,y,theta,r1,r2,é\n"
                                                  + "\n".join(r + ",1" for r in rows))
                                    .encode("latin-1"))], must_flag=False)
    fit("utf-8 BOM", [csv_from("bom.csv", "\ufeff" + good.read_text())], must_flag=False)
    fit("CRLF", [csv_from("crlf.csv", good.read_text().replace("\n", "\r\n"))], must_flag=False)
    fit("tabs", [csv_from("tabs.csv", good.read_text().replace(",", "\t"))], must_flag=False)
    fit("semicolons + decimal comma",
        [csv_from("semi.csv", good.read_text().replace(",", ";").replace(".", ","))],
        must_flag=False)
    fit("quoted header", [csv_from("quoted.csv", ",".join(f'"{h}"' for h in cols) + "\n"
                                   + "\n".join(rows) + "\n")], must_flag=False)
    fit("comment lines", [csv_from("comment.csv", "# recorded 2026-01-01\n# rig 3\n"
                                   + good.read_text())], must_flag=False)
    fit("symlink loop", [root / "loop.csv"])
    with contextlib.suppress(OSError):
        os.symlink(root / "loop.csv", root / "loop.csv")
    fit("same file twice", [good, good])
    dup = root / "copy.csv"
    shutil.copy(good, dup)
    fit("same content twice", [good, dup])
    fit("blank lines between rows", [csv_from("blank.csv", header + "\n" + "\n\n".join(rows))],
        must_flag=False)
    fit("trailing commas", [csv_from("trail.csv", header + ",\n" + ",\n".join(rows) + ",\n")],
        must_flag=False)
    fit("semicolon separated", [csv_from("semi2.csv", good.read_text().replace(",", ";"))],
        must_flag=False)

    # --- header / column faults
    fit("missing theta", [table_csv("notheta.csv", np.delete(table, c["theta"], 1),
                                    [h for h in cols if h != "theta"])])
    fit("missing t", [table_csv("not.csv", np.delete(table, c["t"], 1),
                                [h for h in cols if h != "t"])])
    fit("duplicate column", [table_csv("dupcol.csv", np.c_[table, table[:, c["x"]]],
                                       cols + ["x"])])
    fit("upper-case header", [table_csv("upper.csv", table, [h.upper() for h in cols])],
        must_flag=False)
    fit("no header", [csv_from("nohead.csv", "\n".join(rows) + "\n")])
    fit("wrong --links (5 for 2 joints)", [good], links="5")
    fit("--links 1", [good], links="1")
    fit("--links 0", [good], links="0")
    fit("--links -3", [good], links="-3")
    fit("--links abc", [good], links="abc")
    fit("--links missing", [good], links=None, must_flag=False)

    # --- value faults
    def mutate(name, fn, must_flag=True, fname=None):
        tab = table.copy()
        tab = fn(tab)
        fit(name, [table_csv(fname or f"m{len(cases)}.csv", tab)], must_flag=must_flag)

    def setcol(col, f):
        def g(tab):
            tab[:, col] = f(tab[:, col])
            return tab
        return g

    bad_row = rows[5].split(",")
    bad_row[2] = "abc"
    fit("text cell", [csv_from("text.csv", "\n".join([header, *rows[:5], ",".join(bad_row),
                                                      *rows[6:]]) + "\n")])
    mutate("inf cell", setcol(c["x"], lambda v: np.where(np.arange(len(v)) == 10, np.inf, v)))
    mutate("all-NaN column r1", setcol(c["r1"], lambda v: v * np.nan))
    mutate("all-NaN x", setcol(c["x"], lambda v: v * np.nan))
    mutate("constant r1", setcol(c["r1"], lambda v: v * 0 + 0.3))
    mutate("constant r all", lambda t: (t.__setitem__((slice(None), rcols), 0.1), t)[1])
    mutate("t decreasing", setcol(c["t"], lambda v: v[::-1].copy()))
    mutate("t duplicated", setcol(c["t"], lambda v: np.repeat(v[::2], 2)[:len(v)]))
    mutate("t jitter 20%", setcol(c["t"], lambda v: v + 0.2 * (v[1] - v[0]) *
                                  np.random.default_rng(0).standard_normal(len(v))))
    mutate("t epoch seconds", setcol(c["t"], lambda v: 1.7e9 + v / (2 * np.pi)),
           must_flag=False)
    mutate("t in milliseconds", setcol(c["t"], lambda v: v * 1000), must_flag=False)
    mutate("t all zero", setcol(c["t"], lambda v: v * 0))
    mutate("t has NaN", setcol(c["t"], lambda v: np.where(np.arange(len(v)) == 7, np.nan, v)))
    mutate("degrees r (large)", lambda t: (t.__setitem__((slice(None), rcols),
                                                          np.degrees(t[:, rcols])), t)[1])
    mutate("degrees r (small amplitude)", lambda t: (t.__setitem__(
        (slice(None), rcols), np.degrees(t[:, rcols]) * 0.1), t)[1])
    mutate("wrapped r", lambda t: (t.__setitem__((slice(None), rcols), np.angle(np.exp(
        1j * (t[:, rcols] + 2.8)))), t)[1], must_flag=False)
    mutate("x,y in millimetres", lambda t: (t.__setitem__((slice(None), [c["x"], c["y"]]),
                                                          t[:, [c["x"], c["y"]]] * 85), t)[1])
    mutate("x,y in pixels", lambda t: (t.__setitem__((slice(None), [c["x"], c["y"]]),
                                                     t[:, [c["x"], c["y"]]] * 400 + 640), t)[1])
    mutate("theta in degrees", setcol(c["theta"], np.degrees))
    mutate("huge values", setcol(c["x"], lambda v: v * 1e300))
    mutate("tiny values", lambda t: (t.__setitem__((slice(None), rcols), t[:, rcols] * 1e-12),
                                     t)[1])
    mutate("NaN rows 50%", lambda t: (t.__setitem__((slice(None, None, 2), slice(1, None)),
                                                    np.nan), t)[1])
    mutate("only 2 cycles", lambda t: t[: len(t) // 8])
    if "power" in c:
        mutate("negative power", setcol(c["power"], lambda v: -v))
        mutate("zero power", setcol(c["power"], lambda v: v * 0))
        mutate("power with NaN", setcol(c["power"], lambda v: np.where(
            np.arange(len(v)) % 9 == 0, np.nan, v)), must_flag=False)
    if "trial" in c:
        fit("trial non-integer", [csv_from("tr.csv", good.read_text().replace("\n0,", "\n0.5,"))])
        fit("trial text", [csv_from("trtext.csv", good.read_text().replace("\n1,", "\nb,"))])

    # --- several recordings
    half = table_csv("half.csv", table[: len(table) * 2 // 3])
    fit("two recordings of different lengths", [good, half], must_flag=False)
    fit("three of different lengths, per trial", [good, half, table_csv(
        "third.csv", table[: len(table) // 2])], "--set", "estimator.pool=false", must_flag=False)
    fit("recordings with different joint counts", [good, table_csv(
        "fewer.csv", np.delete(table, rcols[-1], 1), [h for h in cols if h != f"r{len(rcols)}"])])

    # video-rate recordings (12-20 samples per cycle) of different lengths and gaps
    rates = []
    for j, (spc, cyc) in enumerate(((12, 14), (12, 9), (12, 7), (20, 8))):
        sd = np.array([10 + j])
        tr = observe(simulate(NLinkSwimmer(5), circle_gait(5, 0.7), eta=0.025,
                              n_cycles=cyc, samples_per_cycle=spc, seeds=sd), 0.002,
                     dropout=0.03 * j, seeds=sd)
        rates.append(root / f"rate{spc}_{cyc}.csv")
        write_csv(tr, rates[-1])
    fit("3 video-rate recordings, pooled", rates[:3], must_flag=False, links="5")
    fit("3 video-rate recordings, per trial", rates[:3], "--set", "estimator.pool=false",
        must_flag=False, links="5")
    fit("2 video-rate recordings, fixed complexity", rates[:2], "--complexity", "fixed",
        must_flag=False, links="5")
    fit("recordings at different frame rates", rates[2:], must_flag=False, links="5")
    fit("3 video-rate recordings, pooled, no metric", rates[:3], "--metric", "no",
        must_flag=False, links="5")
    fit("2 video-rate recordings, fixed, no metric", rates[:2], "--complexity", "fixed",
        "--metric", "no", must_flag=False, links="5")
    gap = table.copy()
    gap[100:260, 2:] = np.nan  # a gap of 5 cycles in trial 0
    fit("a long gap", [table_csv("gap.csv", gap)], must_flag=False)
    lead = table.copy()
    lead[:40, 2:] = np.nan  # the first cycle missing
    fit("leading NaN rows", [table_csv("lead.csv", lead)], must_flag=False)
    fit("one trial only 1 cycle long", [good, table_csv("short1.csv", table[:33])])

    # --- output folders
    foreign = root / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("my notes")
    cases.append(Case("--out a folder of the user's files", "fit",
                      [str(good), "--links", "3", "--out", str(foreign), "--no-figures"],
                      True, foreign))
    cases.append(Case("--out under a file", "fit",
                      [str(good), "--links", "3", "--out", str(good / "sub"), "--no-figures"],
                      True, None))
    cases.append(Case("convert: --out a file", "convert",
                      [str(root / "pts.npz"), "--links", "3", "--fps", "30", "--out", str(good)],
                      True, None))

    # --- flags
    fit("--out is a file", [good], "--out", str(good))
    fit("--grid 1", [good], "--grid", "1")
    fit("--folds 1", [good], "--folds", "1")
    fit("--folds -2", [good], "--folds", "-2")
    fit("--window nan", [good], "--window", "nan")
    fit("--window -1", [good], "--window", "-1")
    fit("--n-bins 0", [good], "--n-bins", "0")
    fit("--n-bins 100000", [good], "--n-bins", "100000")
    fit("--fourier-order -1", [good], "--fourier-order", "-1")
    fit("--phase-order x", [good], "--phase-order", "x")
    fit("--threads 0", [good], "--threads", "0")
    fit("--device bogus", [good], "--device", "bogus")
    fit("--device cuda", [good], "--device", "cuda")
    fit("--set no equals", [good], "--set", "regression.ridge")
    fit("--set unknown", [good], "--set", "regression.ridg=1")
    fit("--set wrong type", [good], "--set", "regression.ridge=abc")
    fit("--set negative ridge", [good], "--set", "regression.ridge=-1")
    fit("--set nan ridge", [good], "--set", "regression.ridge=nan")
    fit("--set unknown section", [good], "--set", "bogus.x=1")
    fit("--config missing", [good], "--config", str(root / "none.toml"))
    fit("--config folder", [good], "--config", str(root))
    fit("--config invalid", [good], "--config", str(csv_from("bad.toml", "[estimator\nx=1")))
    fit("--config BOM", [good], "--config", str(csv_from(
        "bom.toml", "\ufeff[estimator]\npool = true\n")), must_flag=False)
    fit("--config empty", [good], "--config", str(csv_from("empty.toml", "")), must_flag=False)
    fit("--config wrong type", [good], "--config", str(csv_from(
        "type.toml", "[estimator]\npool = 'yes'\n")))
    fit("--config unknown key", [good], "--config", str(csv_from(
        "unk.toml", "[estimator]\npoool = true\n")))
    fit("--known bad", [good], "--known", "ambient_flow:u_x=abc")
    fit("--known unknown effect", [good], "--known", "wind:u=1")
    keep = [j for j, h in enumerate(cols) if h != "power"]
    fit("--metric yes without power", [table_csv("nopower.csv", table[:, keep],
                                                 [cols[j] for j in keep])], "--metric", "yes")

    # --- convert
    def conv(name, sources, *extra, must_flag=True):
        k[0] += 1
        out = root / f"out{k[0]}"
        cases.append(Case(name, "convert", [str(s) for s in sources]
                          + ["--links", "3", "--out", str(out), *extra], must_flag, out))

    conv("convert: missing file", [root / "nope.h5"])
    conv("convert: empty csv", [root / "empty.csv"])
    conv("convert: garbage", [root / "garbage.csv"])
    conv("convert: trajectory csv given", [good])
    conv("convert: folder", [root])
    pts = root / "pts.npz"
    t = np.arange(300) / 30
    xs = np.linspace(0, 1, 5)[None, :] + 0.01 * t[:, None]
    ys = 0.1 * np.sin(2 * np.pi * (t[:, None] - xs))
    np.savez(pts, points=np.stack([xs, ys], -1))
    conv("convert: npz without fps", [pts], must_flag=False)
    conv("convert: npz, fps 0", [pts], "--fps", "0")
    conv("convert: npz, fps -30", [pts], "--fps", "-30")
    conv("convert: npz, fps nan", [pts], "--fps", "nan")
    conv("convert: npz, scale 0", [pts], "--fps", "30", "--scale", "0")
    conv("convert: npz, min-score 2", [pts], "--fps", "30", "--min-score", "2")
    conv("convert: npz, max-gap -1", [pts], "--fps", "30", "--max-gap", "-1")
    conv("convert: npz, keypoints unknown", [pts], "--fps", "30", "--keypoints", "a,b,c")
    conv("convert: npz, links 2 (even, center)", [pts], "--fps", "30", "--links", "2")
    conv("convert: npz, too few keypoints", [pts], "--fps", "30", "--links", "9")
    np.savez(root / "bad.npz", points=np.zeros((10, 5)))
    conv("convert: npz wrong shape", [root / "bad.npz"], "--fps", "30")
    np.savez(root / "nanpts.npz", points=np.full((300, 5, 2), np.nan))
    conv("convert: npz all NaN", [root / "nanpts.npz"], "--fps", "30")
    (root / "a").mkdir(exist_ok=True)
    (root / "b").mkdir(exist_ok=True)
    shutil.copy(pts, root / "a" / "fish.npz")
    shutil.copy(pts, root / "b" / "fish.npz")
    conv("convert: two files with one name", [root / "a" / "fish.npz", root / "b" / "fish.npz"],
         "--fps", "30", must_flag=False)
    conv("convert: --config BOM", [pts], "--fps", "30", "--config", str(csv_from(
        "cbom.toml", "\ufeff[convert]\ncurve = 'spline'\n")), must_flag=False)
    conv("convert: --set bad", [pts], "--fps", "30", "--set", "convert.curve=zigzag")
    conv("convert: h5 garbage", [csv_from("garbage.h5", os.urandom(2000))])
    conv("convert: wcon garbage", [csv_from("garbage.wcon", "{not json")])
    conv("convert: wcon empty json", [csv_from("empty.wcon", "{}")])
    conv("convert: dlc csv truncated", [csv_from("dlc.csv",
                                                 "scorer,DLC,DLC\nbodyparts,head,head\n")])

    conv("convert: points csv with text", [csv_from("ptstext.csv", "x0,y0,x1,y1\n1,2,a,4\n")],
         "--fps", "30")
    conv("convert: --links 0", [pts], "--fps", "30", "--links", "0")
    conv("convert: --head sideways", [pts], "--fps", "30", "--head", "sideways")
    conv("convert: --track -1", [pts], "--fps", "30", "--track", "-1")
    conv("convert: --fps inf", [pts], "--fps", "inf")
    conv("convert: --config missing", [pts], "--fps", "30", "--config", str(root / "no.toml"))
    conv("convert: --config wrong type", [pts], "--fps", "30", "--config", str(csv_from(
        "ctype.toml", "[convert]\nmax_gap = 'long'\n")))
    conv("convert: --config unknown key", [pts], "--fps", "30", "--config", str(csv_from(
        "cunk.toml", "[convert]\nmax_gapp = 1\n")))
    conv("convert: same source twice", [pts, pts], "--fps", "30")

    # --- discrepancy
    def disc(name, files, *extra, must_flag=True):
        k[0] += 1
        out = root / f"out{k[0]}"
        cases.append(Case(name, "discrepancy", [str(f) for f in files]
                          + ["--out", str(out), "--no-figures", "--quiet", *extra],
                          must_flag, out))

    disc("discrepancy: no --links", [good])
    disc("discrepancy: --links 4 for 2 joints", [good], "--links", "4")
    disc("discrepancy: negative drag ratio", [good], "--links", "3", "--drag-ratio", "-2")
    disc("discrepancy: nan drag ratio", [good], "--links", "3", "--drag-ratio", "nan")
    disc("discrepancy: link lengths count", [good], "--links", "3", "--link-lengths", "1", "2")
    disc("discrepancy: negative link length", [good], "--links", "3", "--link-lengths",
         "0.5", "-0.2", "0.7")
    disc("discrepancy: alpha 2", [good], "--links", "3", "--alpha", "2")
    disc("discrepancy: alpha -0.1", [good], "--links", "3", "--alpha", "-0.1")
    disc("discrepancy: folds 1", [good], "--links", "3", "--folds", "1")
    disc("discrepancy: folds -3", [good], "--links", "3", "--folds", "-3")
    disc("discrepancy: config wrong type", [good], "--links", "3", "--config", str(csv_from(
        "dtype.toml", "[discrepancy]\nalpha = 'high'\n")))
    disc("discrepancy: config negative", [good], "--links", "3", "--config", str(csv_from(
        "dneg.toml", "[discrepancy]\nfolds = -4\n")))
    disc("discrepancy: config unknown", [good], "--links", "3", "--config", str(csv_from(
        "dunk.toml", "[discrepancy]\nalpah = 0.1\n")))
    disc("discrepancy: config BOM", [good], "--links", "3", "--config", str(csv_from(
        "dbom.toml", "\ufeff[discrepancy]\n")), must_flag=False)
    disc("discrepancy: known bad", [good], "--links", "3", "--known", "time_lag:tau=abc")
    disc("discrepancy: empty file", [root / "empty.csv"], "--links", "3")
    disc("discrepancy: good recording, 3 links", [good], "--links", "3", must_flag=False)

    disc("discrepancy: --candidates none valid", [good], "--links", "3", "--candidates",
         "wind")
    disc("discrepancy: alpha nan", [good], "--links", "3", "--alpha", "nan")
    disc("discrepancy: --frame bogus", [good], "--links", "3", "--frame", "bogus")
    disc("discrepancy: --threads -1", [good], "--links", "3", "--threads", "-1")
    disc("discrepancy: --device bogus", [good], "--links", "3", "--device", "tpu")
    disc("discrepancy: same file twice", [good, good], "--links", "3")
    disc("discrepancy: text cell", [root / "text.csv"], "--links", "3")
    disc("discrepancy: negative power", [next(root.glob("m*.csv"))], "--links", "3",
         must_flag=False)
    disc("discrepancy: config not toml", [good], "--links", "3", "--config", str(csv_from(
        "dnot.toml", "alpha: 0.1\n")))
    disc("discrepancy: config folds float", [good], "--links", "3", "--config", str(csv_from(
        "dfl.toml", "[discrepancy]\nfolds = 2.5\n")))

    # --- improve
    def imp(name, *argv, must_flag=True):
        k[0] += 1
        out = root / f"out{k[0]}"
        cases.append(Case(name, "improve", [*argv, "--out", str(out)], must_flag, out))

    imp("improve: negative omega", "simulate", "--omega", "-0.1", "--rounds", "1")
    imp("improve: nan omega", "simulate", "--omega", "nan", "--rounds", "1")
    imp("improve: 100-rad circle", "simulate", "--radius", "100", "--rounds", "1")
    imp("improve: zero radius", "simulate", "--radius", "0", "--rounds", "1")
    imp("improve: rounds 0", "simulate", "--rounds", "0")
    imp("improve: rounds -1", "simulate", "--rounds", "-1")
    imp("improve: trials 0", "simulate", "--trials", "0", "--rounds", "1")
    imp("improve: cycles 1", "simulate", "--cycles", "1", "--rounds", "1")
    imp("improve: links 1", "simulate", "--links", "1", "--rounds", "1")
    imp("improve: links 200", "simulate", "--links", "200", "--rounds", "1")
    imp("improve: scale -1", "simulate", "--scale", "-1", "--rounds", "1")
    imp("improve: scale inf", "simulate", "--scale", "inf", "--rounds", "1")
    imp("improve: propose missing", "propose", str(root / "nope.csv"), "--links", "3")
    imp("improve: propose empty", "propose", str(root / "empty.csv"), "--links", "3")
    imp("improve: propose wrong links", "propose", str(good), "--links", "5")
    imp("improve: propose scale 0", "propose", str(good), "--links", "3", "--scale", "0")

    imp("improve: omega inf", "simulate", "--omega", "inf", "--rounds", "1")
    imp("improve: seed -1", "simulate", "--seed", "-1", "--rounds", "1")
    imp("improve: trials -2", "simulate", "--trials", "-2", "--rounds", "1")
    imp("improve: radius nan", "simulate", "--radius", "nan", "--rounds", "1")
    imp("improve: radius -0.5", "simulate", "--radius", "-0.5", "--rounds", "1")
    imp("improve: propose garbage", "propose", str(root / "garbage.csv"), "--links", "3")
    imp("improve: propose folder", "propose", str(root), "--links", "3")
    imp("improve: propose same twice", "propose", str(good), str(good), "--links", "3")
    imp("improve: propose scale nan", "propose", str(good), "--links", "3", "--scale", "nan")
    imp("improve: propose objective bogus", "propose", str(good), "--links", "3",
        "--objective", "speed")

    # --- sweep
    def sweep(name, text, *extra, must_flag=True):
        k[0] += 1
        out = root / f"out{k[0]}"
        cfg = csv_from(f"sweep{k[0]}.toml", text) if text is not None else None
        argv = (["--config", str(cfg)] if cfg else []) + ["--out", str(out), "--quiet",
                                                           "--no-figures", *extra]
        cases.append(Case(name, "sweep", argv, must_flag, out))

    base = ('name = "b"\nseed = 3\nerror_bins = 12\n[simulation]\nn_cycles = 5\n'
            'samples_per_cycle = 32\n[estimator.regression]\nn_bins = 16\nfourier_order = 4\n'
            '[[experiment]]\nsystem = "3link"\nnoise_kind = "system"\nlevels = [1.0]\n'
            'trials = 2\n')
    sweep("sweep: BOM config", "\ufeff" + base, must_flag=False)
    sweep("sweep: negative level", base.replace("levels = [1.0]", "levels = [-1.0]"))
    sweep("sweep: nan level", base.replace("levels = [1.0]", "levels = [nan]"))
    sweep("sweep: string level", base.replace("levels = [1.0]", 'levels = ["x"]'))
    sweep("sweep: trials 0", base.replace("trials = 2", "trials = 0"))
    sweep("sweep: cycles -5", base.replace("n_cycles = 5", "n_cycles = -5"))
    sweep("sweep: samples 3", base.replace("samples_per_cycle = 32", "samples_per_cycle = 3"))
    sweep("sweep: unknown system", base.replace('"3link"', '"4link"'))
    sweep("sweep: empty config", "")
    sweep("sweep: not toml", "this is not toml")
    sweep("sweep: config missing", None, "--config", str(root / "missing.toml"))
    sweep("sweep: config folder", None, "--config", str(root))
    sweep("sweep: --trials -1", base, "--trials", "-1")
    sweep("sweep: --workers 0 (in-process)", base, "--workers", "0", must_flag=False)
    sweep("sweep: --block 3", base, "--block", "3")
    sweep("sweep: --out a file", base, "--out", str(good))
    sweep("sweep: unknown key", base + "bogus = 1\n")
    sweep("sweep: levels not a list", base.replace("levels = [1.0]", "levels = 1.0"))
    sweep("sweep: noise kind bogus", base.replace('noise_kind = "system"', 'noise_kind = "x"'))
    sweep("sweep: seed text", base.replace("seed = 3", 'seed = "three"'))
    sweep("sweep: seed negative", base.replace("seed = 3", "seed = -3"))
    sweep("sweep: error_bins 0", base.replace("error_bins = 12", "error_bins = 0"))
    sweep("sweep: n_bins 2", base.replace("n_bins = 16", "n_bins = 2"))
    sweep("sweep: no experiment", base.split("[[experiment]]")[0])
    sweep("sweep: --set bad", base, "--set", "simulation.n_cycles")
    sweep("sweep: --set unknown", base, "--set", "simulation.ncycles=3")
    sweep("sweep: --cycles 0", base, "--cycles", "0")
    sweep("sweep: --device bogus", base, "--device", "gpu")
    sweep("sweep: --threads 0", base, "--threads", "0")
    sweep("sweep: BOM + CRLF", "\ufeff" + base.replace("\n", "\r\n"), must_flag=False)
    return cases


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--log", type=Path, help="write every case's exit code and output here")
    p.add_argument("--only", help="run the cases whose name contains this")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    counts: dict[str, int] = {}
    log = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = build_cases(Path(tmp))
        if args.only:
            cases = [c for c in cases if args.only in c.name]
        start = time.perf_counter()
        for case in cases:
            verdict, code, text = run_case(case)
            counts[verdict] = counts.get(verdict, 0) + 1
            first = next((ln for ln in text.splitlines() if "error" in ln.lower()
                          or "warning" in ln.lower()), text.strip().splitlines()[-1:] or [""])
            first = first if isinstance(first, str) else first[0]
            print(f"{verdict:>9}  {str(code):>4}  {case.command:<11} {case.name:<45} "
                  f"{first[:140]}", flush=True)
            log.append(f"## {case.name} [{case.command}] -> {verdict}, exit {code}\n"
                       f"argv: {case.argv}\n{text}\n")
    print(f"\n{len(cases)} cases in {time.perf_counter() - start:.0f} s: "
          + ", ".join(f"{v} {n}" for v, n in sorted(counts.items())))
    if args.log:
        args.log.write_text("\n".join(log))
    return 0


if __name__ == "__main__":
    sys.exit(main())
