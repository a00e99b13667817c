"""The README's tracked-video example runs as written, and prints what the README says it does."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .common import README, code_blocks

SECTION = "## Your first tracked video"


def example_commands() -> list[str]:
    """The bash block of the README's tracked-video section, one command per line."""
    text = README.read_text(encoding="utf-8")
    start = text.index(SECTION)
    line = text.count("\n", 0, start) + 1
    block = next(code for at, code in code_blocks(README, "bash") if at > line)
    return [c for c in block.splitlines() if c.strip() and not c.startswith("#")]


def quoted_output() -> str:
    """The README's text between the example and the next section."""
    text = README.read_text(encoding="utf-8")
    start = text.index(SECTION)
    return text[start:text.index("\n## ", start + 1)]


def test_the_example_is_three_commands_on_the_shipped_recording():
    commands = example_commands()
    assert len(commands) == 3
    assert commands[0].startswith("python -m torchconn.datasets prickleback")
    assert commands[1].startswith("torchconn-convert ") and commands[2].startswith("torchconn-fit ")


@pytest.mark.slow
def test_the_readme_example_runs_and_prints_what_the_readme_quotes(tmp_path):
    bindir = str(Path(sys.executable).parent)
    if shutil.which("torchconn-fit", path=bindir) is None:
        pytest.skip(f"torchconn's commands are not installed in {bindir}")
    env = dict(os.environ, PATH=bindir + os.pathsep + os.environ.get("PATH", ""),
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(README.parent), env.get("PYTHONPATH")) if p)
    printed = ""
    for command in example_commands():
        proc = subprocess.run(command.replace("python ", f"{sys.executable} ", 1), shell=True,
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{command}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
        printed += proc.stdout
    assert (tmp_path / "fitted" / "report.html").is_file()
    readme, said = quoted_output(), re.sub(r"\s+", " ", printed)
    # every line the README quotes from the output, in backticks or its table, is printed so
    quotes = re.findall(r"`([^`]*(?:frames|cycles|Hz|determined)[^`]*)`", readme)
    table = re.search(r"```text\n(.*?)```", readme, re.S).group(1).splitlines()[1:]
    assert len(quotes) >= 3 and len(table) >= 3
    for quote in quotes + table:
        assert re.sub(r"\s+", " ", quote.strip()) in said, quote
