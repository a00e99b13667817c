"""TubeRegression: the tube stage's options and fit."""

import pytest

from torchconn import TubeRegression


def test_intercept_order_above_the_bins_is_refused():
    with pytest.raises(ValueError, match="intercept_order must satisfy 2\\*intercept_order < n_bins=48"):
        TubeRegression(intercept_order=24)
    with pytest.raises(ValueError, match="intercept_order"):
        TubeRegression(intercept_order="high")
