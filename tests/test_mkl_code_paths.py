"""The numerics tests pass on both of MKL's code paths.

On a CPU with AVX-512, MKL takes its AVX-512 kernels by default; ``MKL_ENABLE_INSTRUCTIONS=AVX2``
selects the AVX2 ones, which round differently and converge differently on hard matrices. The
suite itself runs on the default path; this test runs the ``numerics`` tests (marked by path
in tests/conftest.py) again on the other one, in a subprocess started when the suite has been
collected, beside the single-threaded suite. By hand::

    MKL_ENABLE_INSTRUCTIONS=AVX2 python -m pytest -q -m "numerics and not slow"
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

TESTS = Path(__file__).resolve().parent


def _has_avx512() -> bool:
    try:
        return "avx512f" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def wanted() -> bool:
    """Whether the other code path exists here and this run is not already on it."""
    return (torch.backends.mkl.is_available() and _has_avx512()
            and os.environ.get("MKL_ENABLE_INSTRUCTIONS", "").upper() != "AVX2")


#: the AVX2 run, started as soon as the suite is collected (tests/conftest.py, :func:`start`)
#: so that it runs on the core the single-threaded suite leaves idle
_RUN: subprocess.Popen | None = None


def start() -> None:
    """Start the numerics tests on MKL's AVX2 path in a subprocess (once; where wanted)."""
    global _RUN
    if _RUN is None and wanted():
        env = {**os.environ, "MKL_ENABLE_INSTRUCTIONS": "AVX2", "OMP_NUM_THREADS": "1"}
        _RUN = subprocess.Popen(
            [sys.executable, "-m", "pytest", "-q", "-m", "numerics and not slow", "-p",
             "no:cacheprovider", str(TESTS)],
            cwd=TESTS.parent, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True)


def stop() -> None:
    """End the AVX2 run if the suite ends before its test waited for it."""
    if _RUN is not None and _RUN.poll() is None:
        _RUN.kill()
        _RUN.communicate()


@pytest.mark.skipif(not torch.backends.mkl.is_available(), reason="torch is built without MKL")
@pytest.mark.skipif(not _has_avx512(),
                    reason="no AVX-512 on this CPU: MKL's default path is already its AVX2 one")
@pytest.mark.skipif(os.environ.get("MKL_ENABLE_INSTRUCTIONS", "").upper() == "AVX2",
                    reason="this run is already on the AVX2 path")
def test_numerics_pass_on_mkls_avx2_code_path():
    start()  # already running where the suite started it
    try:
        output, _ = _RUN.communicate(timeout=1800)
    except subprocess.TimeoutExpired:
        stop()
        raise
    tail = "\n".join(output.splitlines()[-30:])
    assert _RUN.returncode == 0, f"numerics tests fail on MKL's AVX2 path:\n{tail}"
    assert " passed" in tail
