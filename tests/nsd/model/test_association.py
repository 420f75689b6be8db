"""Appearance association: known permutations, extremes, gradients."""

from __future__ import annotations

import itertools

import pytest
import torch

from nsd.model.association import (
    appearance_similarity,
    apply_association,
    association_softmax,
    exclude_absent,
    hard_association,
)
from tests.base import BaseTester


class TestAssociation(BaseTester):
    @pytest.mark.parametrize("perm", list(itertools.permutations(range(3))))
    def test_picks_the_right_permutation(self, perm):
        g = torch.Generator().manual_seed(0)
        app = torch.randn(1, 3, 128, generator=g)
        source = app[:, list(perm)] + 0.05 * torch.randn(1, 3, 128, generator=g)
        M = appearance_similarity(app, source)
        A = association_softmax(M)
        H = hard_association(M)
        windows = torch.arange(3.0).view(1, 3, 1) + torch.zeros(1, 3, 5)  # window i holds value i
        reordered = apply_association(H, windows[:, list(perm)])
        self.assert_close(reordered, windows)
        assert (A.argmax(-1) == H.argmax(-1)).all()
        assert (A.max(-1).values > 0.9).all()  # beta = 10 makes it sharp for distinct vectors

    def test_only_first_dims_compared(self):
        a = torch.zeros(1, 1, 128)
        b = torch.zeros(1, 1, 128)
        a[..., 0] = b[..., 0] = 1.0
        a[..., 100] = 50.0  # beyond the 16 compared dims
        assert appearance_similarity(a, b).item() == pytest.approx(1.0, abs=1e-3)

    def test_rows_sum_to_one_and_soft_reorder(self):
        M = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
        A = association_softmax(M, beta=1.0)
        self.assert_close(A.sum(-1), torch.ones(1, 2))
        out = apply_association(A, torch.tensor([[[2.0], [4.0]]]))
        e = torch.e
        self.assert_close(out[0, 0, 0], (2 * e + 4) / (e + 1))

    def test_zero_and_identical_vectors(self):
        z = torch.zeros(2, 3, 128, requires_grad=True)
        M = appearance_similarity(z, z)
        assert torch.equal(M, torch.zeros(2, 3, 3))
        A = association_softmax(M)
        self.assert_close(A, torch.full((2, 3, 3), 1 / 3))
        A.sum().backward()
        assert torch.isfinite(z.grad).all()
        same = torch.ones(1, 2, 128)
        self.assert_close(
            association_softmax(appearance_similarity(same, same)), torch.full((1, 2, 2), 0.5)
        )

    @pytest.mark.parametrize("beta", [0.1, 1.0, 10.0, 1e3])
    def test_beta_extremes_finite(self, beta):
        app = torch.randn(2, 4, 128, requires_grad=True)
        A = association_softmax(appearance_similarity(app, app.flip(1)), beta)
        A.pow(2).sum().backward()
        assert torch.isfinite(A).all() and torch.isfinite(app.grad).all()
        self.assert_close(A.sum(-1), torch.ones(2, 4))

    def test_gradcheck(self):
        a = torch.randn(1, 3, 20)
        b = torch.randn(1, 3, 20)
        x = torch.randn(1, 3, 4)
        assert self.gradcheck(
            lambda a, b, x: apply_association(association_softmax(appearance_similarity(a, b)), x),
            [a, b, x],
        )

    @pytest.mark.parametrize("beta", [1.0, 10.0, 1e3])
    def test_absent_sources_get_no_weight(self, beta):
        """A switched-off source window supplies no target slot, however similar it is."""
        g = torch.Generator().manual_seed(1)
        app = torch.randn(2, 4, 128, generator=g)
        M = appearance_similarity(app, app)  # each target window is its own best source
        present = torch.tensor([[True, False, True, False], [False, False, False, True]])
        A = association_softmax(exclude_absent(M, present), beta)
        off = A[~present[:, None, :].expand_as(A)]
        assert off.numel() == 4 * 5 and torch.equal(off, torch.zeros(20))
        self.assert_close(A.sum(-1), torch.ones(2, 4))
        H = hard_association(exclude_absent(M, present))
        assert present.gather(1, H.argmax(-1)).all()
        # the present windows keep their softmax among themselves (a slow reference)
        ref = torch.softmax(beta * M[0][:, [0, 2]], -1)
        self.assert_close(A[0][:, [0, 2]], ref)

    def test_all_absent_or_none_leaves_the_association_unchanged(self):
        M = appearance_similarity(torch.randn(1, 3, 128), torch.randn(1, 3, 128))
        A = association_softmax(M)
        self.assert_close(association_softmax(exclude_absent(M, torch.zeros(1, 3, dtype=bool))), A)
        assert exclude_absent(M, None) is M

    def test_exclusion_keeps_the_gradient(self):
        M = torch.randn(1, 3, 3, dtype=torch.float64, requires_grad=True)
        present = torch.tensor([[True, False, True]])
        (g,) = torch.autograd.grad(exclude_absent(M, present).pow(2).sum(), M)
        self.assert_close(g, 2 * (M - 1e4 * (~present)[:, None, :].double()).detach())
