from pathlib import Path

import pytest
import torch

# The suite is made of small batched tensor ops, for which one intra-op thread is fastest and
# keeps timings steady on a shared 2-core machine.
torch.set_num_threads(1)

TESTS = Path(__file__).resolve().parent

#: the numerics test files (factorisations, regressions, smoothing, phase), as paths under
#: tests/: marked ``numerics`` and run again on MKL's AVX2 code path by tests/test_mkl_code_paths.py
NUMERICS = {
    "test_linalg.py",
    "test_scipy_crosschecks.py",
    "phase/test_fourier.py",
    "phase/test_smoothing.py",
    "phase/test_phaser.py",
    "phase/test_limit_cycle.py",
    "regression/test_connection.py",
    "regression/metric/test_tied.py",
    "regression/selection/test_held_out.py",
}


def pytest_collection_modifyitems(items):
    for item in items:
        path = item.path.resolve()
        if path.is_relative_to(TESTS) and path.relative_to(TESTS).as_posix() in NUMERICS:
            item.add_marker(pytest.mark.numerics)
