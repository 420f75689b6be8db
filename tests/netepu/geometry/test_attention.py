"""Vector attention and VCA: known values, the factorised form against NePu's, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from netepu.geometry.attention import (
    PointTransformerBlock,
    VectorCrossAttention,
    fourier_features,
    fourier_size,
    gather_neighbours,
    knn_indices,
    relative_fourier_columns,
    vector_attention,
    vector_cross_attention,
    vector_cross_attention_reference,
)
from tests.base import DTYPES, BaseTester


def _vca_inputs(dtype, B=2, N=7, Q=11, C=16, latent=10, seed=0):
    g = torch.Generator().manual_seed(seed)

    def r(*s):
        return torch.randn(*s, generator=g, dtype=dtype)

    return r(B, latent), r(B, N, C), r(B, N, 2), r(B, N, 1), r(B, Q, 2)


class TestFourier(BaseTester):
    def test_known_values(self):
        d = torch.tensor([[0.5, -1.0]])
        out = fourier_features(d, 2)  # bands 1, 4
        expected = [0.5, -1.0, math.sin(0.5), math.sin(-1.0), math.cos(0.5), math.cos(-1.0),
                    math.sin(2.0), math.sin(-4.0), math.cos(2.0), math.cos(-4.0)]
        self.assert_close(out[0], torch.tensor(expected))
        assert out.shape[-1] == fourier_size(2, 2)

    def test_relative_columns_pick_the_right_features(self):
        delta = torch.randn(5, 3, dtype=torch.float64)
        full = fourier_features(delta, 3)
        rel, ab = relative_fourier_columns(2, 1, 3)
        self.assert_close(full[:, ab], fourier_features(delta[:, 2:], 3))
        # relative layout: [delta (2), sin (3 x 2), cos (3 x 2)]
        bands = torch.linspace(1, 8, 3, dtype=torch.float64)
        fx = (delta[:, None, :2] * bands[:, None]).flatten(1)
        self.assert_close(full[:, rel], torch.cat([delta[:, :2], fx.sin(), fx.cos()], 1))


class TestNeighbours(BaseTester):
    def test_knn_known(self):
        pts = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [5.0, 0.0], [2.0, 0.0]]])
        q = torch.tensor([[[1.9, 0.0]]])
        assert knn_indices(q, pts, 2).tolist() == [[[3, 1]]]
        assert knn_indices(q, pts, 4) is None and knn_indices(q, pts, 0) is None

    def test_gather(self):
        x = torch.arange(12.0).reshape(1, 4, 3)
        idx = torch.tensor([[[2, 0], [1, 1]]])
        out = gather_neighbours(x, idx)
        assert out.shape == (1, 2, 2, 3)
        self.assert_close(out[0, 0, 0], x[0, 2])
        self.assert_close(out[0, 1, 1], x[0, 1])


def _slow_vca(mod: VectorCrossAttention, latent, feats, key_pos, key_abs, query_pos):
    """Per-pixel loops over NePu's VCA equations (obviously correct, slow)."""
    B, N, C = feats.shape
    q = mod.w_q(latent)
    k, v = mod.w_k(feats), mod.w_v(feats)
    kg, vg = mod.w_k_global(latent), mod.w_v_global(latent)
    out = torch.zeros(B, query_pos.shape[1], C, dtype=feats.dtype)
    for b in range(B):
        for i in range(query_pos.shape[1]):
            d2 = ((query_pos[b, i] - key_pos[b]) ** 2).sum(-1)
            nb = d2.argsort()[: mod.k] if 0 < mod.k < N else torch.arange(N)
            logits, vals = [], []
            for j in nb:
                delta = torch.cat([query_pos[b, i] - key_pos[b, j], key_abs[b, j]])
                p = mod.pos_embed(fourier_features(delta, mod.n_freq))
                logits.append(mod.mlp(q[b] - k[b, j] + p))
                vals.append(v[b, j] + p)
            logits.append(mod.mlp(q[b] - kg[b]))
            vals.append(vg[b])
            a = torch.softmax(torch.stack(logits), 0).repeat_interleave(C // logits[0].shape[0], -1)
            out[b, i] = (a * torch.stack(vals)).sum(0)
    return out


class TestVectorCrossAttention(BaseTester):
    @DTYPES
    @pytest.mark.parametrize("hidden, groups, k", [(16, 16, 4), (8, 4, 0), (12, 2, 3)])
    def test_factorised_equals_reference(self, dtype, hidden, groups, k):
        torch.manual_seed(0)
        mod = VectorCrossAttention(16, 10, k=k, n_freq=3, hidden=hidden, groups=groups).to(dtype)
        inputs = _vca_inputs(dtype)
        fast = mod(mod.prepare(*inputs[:4]), inputs[4])
        mod.mode = "reference"
        ref = mod(mod.prepare(*inputs[:4]), inputs[4])
        self.assert_close(fast, ref, rtol=1e-4 if dtype == torch.float32 else None,
                          atol=1e-4 if dtype == torch.float32 else None)

    def test_reference_equals_slow_loops(self):
        torch.manual_seed(1)
        mod = VectorCrossAttention(8, 6, k=3, n_freq=2, hidden=8, groups=4,
                                   mode="reference").double()
        latent, feats, kp, ka, qp = _vca_inputs(torch.float64, B=1, N=5, Q=4, C=8, latent=6)
        self.assert_close(mod(mod.prepare(latent, feats, kp, ka), qp),
                          _slow_vca(mod, latent, feats, kp, ka, qp))

    def test_factorised_gradients_match_reference(self):
        torch.manual_seed(2)
        mod = VectorCrossAttention(8, 6, k=3, n_freq=2, hidden=8, groups=2).double()
        inputs = [x.requires_grad_(True) for x in _vca_inputs(torch.float64, C=8, latent=6)]
        grads = []
        for mode in ("factorised", "reference"):
            mod.mode = mode
            mod.zero_grad()
            out = mod(mod.prepare(*inputs[:4]), inputs[4])
            g = torch.autograd.grad((out * torch.linspace(-1, 1, out.numel()).double()
                                     .reshape(out.shape)).sum(), [*inputs, *mod.parameters()])
            grads.append(g)
        for a, b in zip(*grads, strict=True):
            self.assert_close(a, b)

    def test_gradcheck_factorised(self):
        torch.manual_seed(3)
        B, Q, N, H, G, C, F = 1, 3, 4, 4, 2, 4, 1
        E = 2 * (1 + 2 * F)
        r = torch.randn
        inputs = [r(B, Q, 2), r(B, N, 2), r(B, N, H), r(B, N, C), r(B, G), r(B, C), r(H, E),
                  r(G, H), r(G), r(C, E)]
        mask = torch.ones(B, Q, N, dtype=torch.bool)
        mask[0, 0, 1] = False

        def fn(*x):
            return vector_cross_attention(*x, F, mask)

        assert self.gradcheck(fn, inputs)

    def test_gradcheck_reference_and_vector_attention(self):
        torch.manual_seed(4)
        lin = torch.nn.Linear(5, 4).double()
        mlp = torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.ReLU(),
                                  torch.nn.Linear(3, 2)).double()
        r = torch.randn
        gamma, q, k, v, kg, vg = r(1, 2, 3, 5), r(1, 4), r(1, 2, 3, 4), r(1, 2, 3, 4), r(1, 4), \
            r(1, 4)
        assert self.gradcheck(
            lambda *x: vector_cross_attention_reference(*x, lin, mlp), [gamma, q, k, v, kg, vg])
        assert self.gradcheck(lambda *x: vector_attention(*x, mlp),
                              [r(1, 2, 4), r(1, 2, 3, 4), r(1, 2, 3, 4), r(1, 2, 3, 4)])

    def test_attention_weights_sum_to_one(self):
        # constant values -> the output is that constant, whatever the weights
        torch.manual_seed(5)
        B, Q, N, H, G, C, F = 2, 5, 6, 8, 4, 8, 2
        E = 2 * (1 + 2 * F)
        value = torch.ones(B, N, C)
        out = vector_cross_attention(
            torch.randn(B, Q, 2), torch.randn(B, N, 2), torch.randn(B, N, H), value,
            torch.randn(B, G), torch.ones(B, C), torch.randn(H, E), torch.randn(G, H),
            torch.randn(G), torch.zeros(C, E), F)
        self.assert_close(out, torch.ones(B, Q, C))

    def test_mask_excludes_keypoints(self):
        # a masked keypoint's value never reaches the output
        torch.manual_seed(6)
        B, Q, N, H, G, C, F = 1, 3, 4, 4, 2, 4, 1
        E = 2 * (1 + 2 * F)
        args = [torch.randn(B, Q, 2), torch.randn(B, N, 2), torch.randn(B, N, H),
                torch.randn(B, N, C), torch.randn(B, G), torch.randn(B, C), torch.randn(H, E),
                torch.randn(G, H), torch.randn(G), torch.randn(C, E), F]
        mask = torch.ones(B, Q, N, dtype=torch.bool)
        mask[..., 2] = False
        a = vector_cross_attention(*args, mask)
        args[3] = args[3].clone()
        args[3][:, 2] += 100.0
        self.assert_close(vector_cross_attention(*args, mask), a)

    def test_bad_groups(self):
        with pytest.raises(ValueError, match="divide"):
            VectorCrossAttention(10, 4, groups=3)
        with pytest.raises(ValueError, match="mode"):
            VectorCrossAttention(8, 4, mode="fast")


class TestPointTransformerBlock(BaseTester):
    @pytest.mark.parametrize("k", [0, 3])
    def test_permutation_equivariant(self, k):
        torch.manual_seed(0)
        block = PointTransformerBlock(8, 3, k=k, n_freq=2, elementwise_mlp=True).double()
        pos, feats = torch.randn(2, 6, 3, dtype=torch.float64), torch.randn(2, 6, 8,
                                                                            dtype=torch.float64)
        perm = torch.tensor([3, 0, 5, 1, 4, 2])
        self.assert_close(block(pos[:, perm], feats[:, perm]), block(pos, feats)[:, perm])

    def test_gradcheck(self):
        torch.manual_seed(1)
        block = PointTransformerBlock(4, 2, k=2, n_freq=1, groups=2).double()
        pos, feats = torch.randn(1, 4, 2), torch.randn(1, 4, 4)
        assert self.gradcheck(block, [pos, feats], requires_grad=[False, True])
