import pytest
import torch

# The suite is made of small batched tensor ops, for which one intra-op thread is fastest and
# keeps timings steady on a shared 2-core machine.
torch.set_num_threads(1)

#: the numerics test modules (factorisations, regressions, smoothing, phase): marked
#: ``numerics`` and run again on MKL's AVX2 code path by tests/test_mkl_code_paths.py
NUMERICS = {"test_linalg", "test_metric", "test_fourier", "test_smoothing", "test_phase",
            "test_regression", "test_held_out", "test_limit_cycle", "test_scipy_crosschecks"}


def pytest_collection_modifyitems(items):
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in NUMERICS:
            item.add_marker(pytest.mark.numerics)
