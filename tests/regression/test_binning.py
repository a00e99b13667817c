"""Phase bins: the kernel weights of samples in overlapping bins (``assign_bins``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchconn.regression import assign_bins

F64 = torch.float64


# ----------------------------------------------------------------------------- binning
def test_assign_bins_matches_brute_force():
    gen = torch.Generator().manual_seed(1)
    phase = (torch.rand(2, 3, 300, generator=gen, dtype=F64) - 0.3) * 40  # negative, many cycles
    phase[0, 1, ::7] = torch.nan
    m = 7
    for window, kernel in [(0.5, "box"), (0.8, "tricube"), (1.3, "epanechnikov")]:
        bins = assign_bins(phase, m, window=window, kernel=kernel)
        assert bins.index.shape == (2, 3, m, bins.max_count)
        assert bins.max_count == int(bins.count.max())
        h = 2 * math.pi / m
        ph = phase.numpy()
        for idx in np.ndindex(2, 3):
            for k in range(m):
                off = np.remainder(ph[idx] - k * h + math.pi, 2 * math.pi) - math.pi
                inside = np.flatnonzero((off >= -window * h) & (off < window * h))
                got = bins.index[idx + (k,)][: bins.count[idx + (k,)]].numpy()
                assert sorted(got.tolist()) == inside.tolist()
                s = np.abs(off[got]) / (window * h)
                want = {"box": np.ones_like(s), "tricube": (1 - s**3) ** 3,
                        "epanechnikov": 1 - s**2}[kernel]
                np.testing.assert_allclose(bins.weight[idx + (k,)][: len(got)].numpy(), want,
                                           atol=1e-12)
                assert (bins.weight[idx + (k,)][len(got):] == 0).all()
        if window == 0.5:  # a partition: every finite sample in exactly one bin
            assert (bins.count.sum(-1) == torch.isfinite(phase).sum(-1)).all()


def test_assign_bins_validates():
    with pytest.raises(ValueError, match="window"):
        assign_bins(torch.zeros(10, dtype=F64), 4, window=2.0)
    with pytest.raises(ValueError, match="kernel"):
        assign_bins(torch.zeros(10, dtype=F64), 4, kernel="gauss")
    with pytest.raises(ValueError, match="inf"):
        assign_bins(torch.tensor([0.0, math.inf], dtype=F64), 4)
