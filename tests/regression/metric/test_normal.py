"""The corrected normal equations of the metric fit (CorrectedNormal): the floored correction."""

import torch

from torchconn.regression.metric.normal import CorrectedNormal

F64 = torch.float64


def test_floored_correction_against_its_explicit_construction():
    """Directions whose signal fraction ``1 − ν`` falls below the floor keep the share
    ``κ = (1 − floor)/ν`` of the correction on both sides of the normal equations; the others,
    and elements with none below it, keep all of it (``A = G − C``)."""
    g0 = torch.Generator().manual_seed(0)
    p, floor = 6, 0.2
    x = torch.randn(3, 50, p, generator=g0, dtype=F64)
    gram = x.mT @ x
    lower = torch.linalg.cholesky(gram)
    rot, _ = torch.linalg.qr(torch.randn(3, p, p, generator=g0, dtype=F64))
    nu = torch.tensor([[0.1, 0.3, 0.5, 0.7, 0.95, 1.2], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
                       [0.2, 0.5, 0.85, 0.1, 0.0, -0.1]], dtype=F64)
    t = lower @ rot  # G = T Tᵀ, C = T diag(ν) Tᵀ
    corr = t @ torch.diag_embed(nu) @ t.mT
    normal = CorrectedNormal.of(gram, corr, torch.full((3,), floor, dtype=F64))
    share = torch.where(nu > 1 - floor, (1 - floor) / nu, 1.0)
    a = t @ torch.diag_embed(1 - share * nu) @ t.mT
    h = torch.randn(3, p, generator=g0, dtype=F64)
    assert normal.floored.tolist() == [True, False, True]
    torch.testing.assert_close(normal.applied, share.amin(-1))
    torch.testing.assert_close(a[1], gram[1] - corr[1])
    torch.testing.assert_close(normal.solve(h), torch.linalg.solve(a, h))
    torch.testing.assert_close(normal.correction_share(h),
                               (t @ torch.diag_embed(share) @ torch.linalg.inv(t) @ h[..., None])[..., 0])
    chol = normal.cholesky()
    torch.testing.assert_close(chol @ chol.mT, a)
