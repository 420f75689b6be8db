r"""Vector attention over keypoints and vector cross-attention (VCA) from pixels to keypoints.

Both are the point-transformer attention that NePu uses (Giebenhain et al.,
ACCV 2022; NeTePu sec. 3.1). Positional information enters through Fourier
features of relative positions,

.. math::
    \gamma(\Delta) = [\Delta, \sin(\omega_1 \Delta), \cos(\omega_1 \Delta), \dots,
    \sin(\omega_F \Delta), \cos(\omega_F \Delta)],\quad
    \omega = \mathrm{linspace}(1, 2^F, F)

(NePu's frequency bands), embedded by a linear map :math:`p = W_p \gamma + b_p`.

Vector attention (one query token :math:`i`, neighbours :math:`j`)
    .. math::
        a_{ij} = \mathrm{MLP}(q_i - k_j + p_{ij}) \in \mathbb{R}^G,\quad
        \alpha_{ij} = \mathrm{softmax}_j(a_{ij}),\quad
        y_i = \sum_j \alpha_{ij}^{g(c)} \odot (v_j + p_{ij})

    with the MLP ``Linear(C, H) -> ReLU -> Linear(H, G)``. Channel ``c`` of the
    values uses the weight of its group :math:`g(c) = \lfloor c G / C \rfloor`
    (grouped vector attention); NePu has one group per channel (``G = C``,
    ``H = C``).

Vector cross-attention (VCA)
    A query pixel attends to its ``k`` nearest projected keypoints plus one
    global token from the latent code. NePu's query :math:`q` comes from the
    global code, so it is the same for every pixel, and the global token's
    positional term is zero. Two evaluations of the same maths:

    ``reference`` (:func:`vector_cross_attention_reference`)
        NePu's order of operations: per pixel and neighbour, :math:`p_{ij}` is
        embedded to ``C`` channels and the MLP runs on ``C`` channels.
    ``factorised`` (:func:`vector_cross_attention`)
        The first MLP layer is linear, so
        :math:`W_1 (q - k_j + W_p\gamma_{ij} + b_p) = W_1(q - k_j + b_p) + (W_1 W_p)\gamma_{ij}`:
        the first term is computed once per keypoint and shared by all pixels,
        the second is one small matrix product on :math:`\gamma` (E numbers, not C).
        The value's positional term is linear in :math:`\gamma` too and the
        attention weights are shared within a group, so
        :math:`\sum_j \alpha^g_{ij} W_p^{(g)}\gamma_{ij}
        = W_p^{(g)} \sum_j \alpha^g_{ij}\gamma_{ij}`:
        the projection runs once per pixel instead of once per neighbour.
        The per-keypoint part of the offset (NePu: the keypoint's depth) folds
        into per-keypoint terms as well, so only the relative part's features
        (:math:`E_R` numbers) are formed per pixel and neighbour. With ``G = C``
        and ``H = C`` this equals the reference to rounding; the cost per pixel
        and neighbour drops from :math:`E C + 2 C^2` to
        :math:`E_R H + H G + G E_R + C` multiply-adds.

Shapes: ``B`` batch (one image / view each), ``N`` keypoints, ``Q`` query
pixels, ``n`` neighbours, ``C`` channels, ``H`` hidden width of the attention
MLP, ``G`` groups, ``E`` Fourier feature size.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = [
    "PointTransformerBlock",
    "VectorCrossAttention",
    "fourier_features",
    "fourier_size",
    "gather_neighbours",
    "knn_indices",
    "relative_fourier_columns",
    "vector_attention",
    "vector_cross_attention",
    "vector_cross_attention_reference",
]


# ------------------------------------------------------------------ pure functions
def fourier_size(dim: int, n_freq: int) -> int:
    """Size E of :func:`fourier_features` for ``dim``-dimensional offsets."""
    return dim * (1 + 2 * n_freq)


def fourier_features(delta: Tensor, n_freq: int) -> Tensor:
    """NePu's Fourier features :math:`\\gamma(\\Delta)` of relative positions.

    Args:
        delta: offsets, shape (..., D).
        n_freq: number of frequency bands F (bands ``linspace(1, 2**F, F)``).

    Returns:
        Features, shape (..., D * (1 + 2 F)), ordered
        ``[delta, sin(w1 delta), cos(w1 delta), ...]``.

    Example:
        >>> fourier_features(torch.zeros(1, 2), 1).tolist()
        [[0.0, 0.0, 0.0, 0.0, 1.0, 1.0]]
    """
    if n_freq == 0:
        return delta
    bands = torch.linspace(1.0, 2.0**n_freq, n_freq, dtype=delta.dtype, device=delta.device)
    x = delta.unsqueeze(-2) * bands.unsqueeze(-1)  # (..., F, D)
    sc = torch.stack([torch.sin(x), torch.cos(x)], dim=-2)  # (..., F, 2, D)
    return torch.cat([delta, sc.flatten(-3)], dim=-1)


def knn_indices(query: Tensor, points: Tensor, k: int) -> Tensor | None:
    """Indices of the ``k`` nearest ``points`` of every query (Euclidean).

    Args:
        query: shape (B, Q, D).
        points: shape (B, N, D).
        k: number of neighbours; ``k <= 0`` or ``k >= N`` means all points.

    Returns:
        int64 indices, shape (B, Q, k), nearest first; None when every point is
        a neighbour (callers then skip the gather).
    """
    n = points.shape[-2]
    if k <= 0 or k >= n:
        return None
    d2 = torch.cdist(query.detach(), points.detach())
    return d2.topk(k, dim=-1, largest=False, sorted=True).indices


def gather_neighbours(x: Tensor, idx: Tensor | None, n_query: int | None = None) -> Tensor:
    """Per-query neighbour rows of ``x``.

    Args:
        x: per-point values, shape (B, N, C).
        idx: neighbour indices (B, Q, n) from :func:`knn_indices`, or None for all points.
        n_query: Q, needed when ``idx`` is None (the result then broadcasts over Q
            as a (B, 1, N, C) view).

    Returns:
        Shape (B, Q, n, C), or (B, 1, N, C) when ``idx`` is None.
    """
    if idx is None:
        return x.unsqueeze(1)
    B, Q, n = idx.shape
    flat = idx.reshape(B, Q * n, 1).expand(-1, -1, x.shape[-1])
    return torch.gather(x, 1, flat).reshape(B, Q, n, x.shape[-1])


def _group_weights(alpha: Tensor, channels: int) -> Tensor:
    """Expand group weights (..., G) to channels (..., C), C divisible by G."""
    G = alpha.shape[-1]
    if G == channels:
        return alpha
    return alpha.repeat_interleave(channels // G, dim=-1)


def vector_attention(
    query: Tensor, key: Tensor, value: Tensor, pos: Tensor, mlp: nn.Module
) -> Tensor:
    """Vector attention in NePu's order of operations.

    Args:
        query: q, shape (B, Q, C) (or (B, 1, C) to broadcast one query).
        key: gathered keys k_j, shape (B, Q, n, C).
        value: gathered values v_j, shape (B, Q, n, C).
        pos: positional embeddings p_ij, shape (B, Q, n, C).
        mlp: maps (..., C) to logits (..., G), C divisible by G.

    Returns:
        :math:`\\sum_j \\mathrm{softmax}_j(\\mathrm{MLP}(q - k_j + p_{ij})) \\odot (v_j + p_{ij})`,
        shape (B, Q, C).
    """
    logits = mlp(query.unsqueeze(2) - key + pos)
    alpha = _group_weights(torch.softmax(logits, dim=2), value.shape[-1])
    return (alpha * (value + pos)).sum(dim=2)


def vector_cross_attention_reference(
    gamma: Tensor,
    query: Tensor,
    key: Tensor,
    value: Tensor,
    global_key: Tensor,
    global_value: Tensor,
    pos_embed: nn.Linear,
    mlp: nn.Module,
) -> Tensor:
    """VCA of pixels over neighbouring keypoints + a global token, as NePu computes it.

    Args:
        gamma: Fourier features of pixel-to-keypoint offsets, shape (B, Q, n, E).
        query: global query q, shape (B, C).
        key: gathered keypoint keys, shape (B, Q, n, C) (or (B, 1, n, C)).
        value: gathered keypoint values, same shape as ``key``.
        global_key, global_value: the global token, shape (B, C).
        pos_embed: :math:`W_p, b_p`, E -> C.
        mlp: ``Sequential(Linear(C, H), ReLU, Linear(H, G))``.

    Returns:
        Shape (B, Q, C).
    """
    B, Q, n, _ = gamma.shape
    C = query.shape[-1]
    pos = pos_embed(gamma)  # (B, Q, n, C)
    key = key.expand(B, Q, n, C)
    value = value.expand(B, Q, n, C)
    key = torch.cat([key, global_key[:, None, None].expand(B, Q, 1, C)], dim=2)
    value = torch.cat([value, global_value[:, None, None].expand(B, Q, 1, C)], dim=2)
    pos = torch.cat([pos, pos.new_zeros(B, Q, 1, C)], dim=2)
    return vector_attention(query[:, None], key, value, pos, mlp)


def _trig_features(x: Tensor, n_freq: int) -> tuple[Tensor, Tensor]:
    """sin and cos of every band times every coordinate: (..., D) -> 2 x (..., F * D)."""
    bands = torch.linspace(1.0, 2.0**n_freq, n_freq, dtype=x.dtype, device=x.device)
    fx = (x.unsqueeze(-2) * bands.unsqueeze(-1)).flatten(-2)
    return torch.sin(fx), torch.cos(fx)


def relative_fourier_columns(rel_dim: int, abs_dim: int, n_freq: int) -> tuple[list, list]:
    """Columns of :func:`fourier_features` of ``[relative (rel_dim), absolute (abs_dim)]`` offsets.

    Returns:
        ``(relative, absolute)`` column lists. ``relative`` is ordered as
        :func:`vector_cross_attention` lays out its relative features:
        ``[delta (R), sin (F x R), cos (F x R)]``; ``absolute`` in
        :func:`fourier_features` order for the absolute coordinates alone.
    """
    D = rel_dim + abs_dim

    def cols(dims: range) -> tuple[list, list, list]:
        lin = list(dims)
        sin = [D + 2 * D * f + a for f in range(n_freq) for a in dims]
        cos = [D + 2 * D * f + D + a for f in range(n_freq) for a in dims]
        return lin, sin, cos

    rl, rs, rc = cols(range(rel_dim))
    al, as_, ac = cols(range(rel_dim, D))
    absolute = al + [c for f in range(n_freq) for c in (
        as_[f * abs_dim:(f + 1) * abs_dim] + ac[f * abs_dim:(f + 1) * abs_dim])]
    return rl + rs + rc, absolute


def vector_cross_attention(
    query_pos: Tensor,
    key_pos: Tensor,
    hidden_key: Tensor,
    value: Tensor,
    global_logit: Tensor,
    global_value: Tensor,
    w_pos_hidden: Tensor,
    w_logit: Tensor,
    b_logit: Tensor,
    w_pos: Tensor,
    n_freq: int,
    neighbours: Tensor | None = None,
) -> Tensor:
    r"""Factorised grouped VCA (see the module docstring for the algebra).

    The offsets of a pixel to keypoint ``j`` are :math:`(\tilde u - \tilde u_j, a_j)`:
    a *relative* part (R numbers) and a per-keypoint *absolute* part (NePu: the
    keypoint's normalised depth). Every term of the absolute part is folded
    into the per-keypoint inputs ``hidden_key`` and ``value`` by
    :meth:`VectorCrossAttention.prepare`; here only the relative part is
    handled per pixel. Its Fourier features enter the value term through
    :math:`\sin(f(x - x_j)) = \sin fx \cos fx_j - \cos fx \sin fx_j` (and the
    cosine alike), so that all aggregation over keypoints is one batched
    matrix product with per-keypoint rows.

    Args:
        query_pos: relative coordinates of the query pixels, (B, Q, R).
        key_pos: relative coordinates of the keypoints, (B, N, R).
        hidden_key: per-keypoint first-layer terms
            :math:`W_1(q - k_j + p^{abs}_j + b_p) + b_1`, (B, N, H).
        value: per-keypoint values :math:`v_j + p^{abs}_j + b_p`, (B, N, C).
        global_logit: logits of the global token, (B, G).
        global_value: value of the global token, (B, C).
        w_pos_hidden: :math:`W_1 W_p^{rel}`, (H, E_R) with E_R = R (1 + 2F).
        w_logit, b_logit: second MLP layer, (G, H), (G,).
        w_pos: :math:`W_p^{rel}`, (C, E_R), columns ordered as
            :func:`relative_fourier_columns` returns them.
        n_freq: F.
        neighbours: bool (B, Q, N), True for the keypoints a pixel attends to;
            None for all.

    Returns:
        Shape (B, Q, C).
    """
    B, Q, R = query_pos.shape
    N = key_pos.shape[1]
    G, C = w_logit.shape[0], w_pos.shape[0]
    cg = C // G
    delta = query_pos.unsqueeze(2) - key_pos.unsqueeze(1)  # (B, Q, N, R)
    ds, dc = _trig_features(delta, n_freq)
    gamma = torch.cat([delta, ds, dc], dim=-1)  # (B, Q, N, E_R)
    # the (B, Q, N, .) tensors dominate the cost: update them in place
    hidden = (gamma @ w_pos_hidden.T).add_(hidden_key.unsqueeze(1)).relu_()  # (B, Q, N, H)
    logits = torch.matmul(hidden, w_logit.T).add_(b_logit)  # (B, Q, N, G)
    if neighbours is not None:
        logits = logits.masked_fill_(~neighbours.unsqueeze(-1), float("-inf"))
    # softmax over neighbours + global token; the shift by the maximum cancels, so no gradient
    top = torch.maximum(logits.detach().amax(dim=2), global_logit.detach().unsqueeze(1))
    e_nb = logits.sub_(top.unsqueeze(2)).exp_()
    e_gl = torch.exp(global_logit.unsqueeze(1) - top)
    norm = e_nb.sum(dim=2) + e_gl  # (B, Q, G)
    # per-keypoint rows: the group's value channels and the keypoint's trig features
    ks, kc = _trig_features(key_pos, n_freq)
    rows = torch.cat([value.reshape(B, N, G, cg).permute(0, 2, 1, 3),
                      torch.cat([key_pos, kc, ks], -1).unsqueeze(1).expand(B, G, N, -1)], -1)
    agg = e_nb.permute(0, 3, 1, 2) @ rows  # (B, G, Q, cg + R + 2FR)
    a_val, a_lin = agg[..., :cg], agg[..., cg:cg + R]
    a_cos, a_sin = agg[..., cg + R:].chunk(2, dim=-1)
    w0 = e_nb.sum(dim=2).permute(0, 2, 1).unsqueeze(-1)  # (B, G, Q, 1)
    qs, qc = (x.unsqueeze(1) for x in _trig_features(query_pos, n_freq))  # (B, 1, Q, FR)
    qp = query_pos.unsqueeze(1)
    pos = torch.cat([qp * w0 - a_lin, qs * a_cos - qc * a_sin, qc * a_cos + qs * a_sin], -1)
    out = a_val + pos @ w_pos.reshape(G, cg, -1).transpose(-1, -2)  # (B, G, Q, cg)
    out = out + e_gl.permute(0, 2, 1).unsqueeze(-1) * global_value.reshape(B, G, 1, cg)
    out = out / norm.permute(0, 2, 1).unsqueeze(-1)
    return out.permute(0, 2, 1, 3).reshape(B, Q, C)


# ------------------------------------------------------------------ modules
def _attention_mlp(channels: int, hidden: int, groups: int) -> nn.Sequential:
    if channels % groups:
        raise ValueError(f"attention groups ({groups}) must divide the channels ({channels})")
    return nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(), nn.Linear(hidden, groups))


class PointTransformerBlock(nn.Module):
    """Point-transformer block over keypoints: vector attention + residual + LayerNorm.

    NePu's ``TransformerBlock`` (with LayerNorm instead of BatchNorm, so that a
    render does not depend on the batch), optionally followed by an
    element-wise residual MLP (NePu's encoder pairs them).

    Args:
        channels: C.
        pos_dim: D of the positions.
        k: neighbours per token (``<= 0``: all tokens, "full attention").
        n_freq: Fourier bands of the positional encoding.
        hidden: H of the attention MLP (default C).
        groups: G (default C: NePu's per-channel vector attention).
        elementwise_mlp: append a residual two-layer MLP.

    Shape:
        positions (B, N, D), features (B, N, C) -> (B, N, C).
    """

    def __init__(
        self,
        channels: int,
        pos_dim: int,
        k: int = 0,
        n_freq: int = 5,
        hidden: int | None = None,
        groups: int | None = None,
        elementwise_mlp: bool = False,
    ) -> None:
        super().__init__()
        self.k, self.n_freq = k, n_freq
        self.w_q = nn.Linear(channels, channels, bias=False)
        self.w_k = nn.Linear(channels, channels, bias=False)
        self.w_v = nn.Linear(channels, channels, bias=False)
        self.pos_embed = nn.Linear(fourier_size(pos_dim, n_freq), channels)
        self.mlp = _attention_mlp(channels, hidden or channels, groups or channels)
        self.norm = nn.LayerNorm(channels)
        self.ffn = None
        if elementwise_mlp:
            self.ffn = nn.Sequential(
                nn.Linear(channels, channels), nn.ReLU(), nn.Linear(channels, channels), nn.ReLU()
            )
            self.ffn_norm = nn.LayerNorm(channels)

    def forward(self, positions: Tensor, features: Tensor) -> Tensor:
        idx = knn_indices(positions, positions, self.k)
        N = positions.shape[1]
        nb_pos = gather_neighbours(positions, idx)  # (B, N|1, n, D)
        gamma = fourier_features(positions.unsqueeze(2) - nb_pos, self.n_freq)  # (B, N, n, E)
        pos = self.pos_embed(gamma)
        key = gather_neighbours(self.w_k(features), idx).expand(-1, N, -1, -1)
        value = gather_neighbours(self.w_v(features), idx).expand(-1, N, -1, -1)
        y = self.norm(features + vector_attention(self.w_q(features), key, value, pos, self.mlp))
        if self.ffn is not None:
            y = self.ffn_norm(y + self.ffn(y))
        return y


class VectorCrossAttention(nn.Module):
    """VCA from query pixels to their ``k`` nearest keypoints plus a global token.

    The offset of a pixel to keypoint ``j`` is ``(query_pos - key_pos_j, key_abs_j)``
    (NePu: 2D offset in the image and the keypoint's normalised depth).

    Args:
        channels: C (keypoint features and output).
        latent: size of the global code that gives the query and the global token.
        rel_dim: R, size of the relative part of the offset (NePu: 2).
        abs_dim: A, size of the per-keypoint part (NePu: 1).
        k: neighbours per pixel (``<= 0`` or ``>= N``: every keypoint).
        n_freq: Fourier bands.
        hidden: H of the attention MLP (NePu: C).
        groups: G (NePu: C).
        mode: ``"factorised"`` (fast, :func:`vector_cross_attention`) or
            ``"reference"`` (NePu's order, :func:`vector_cross_attention_reference`);
            both compute the same function of the same weights.

    Use :meth:`prepare` once per image, then :meth:`forward` for any number of
    pixel batches.
    """

    MODES = ("factorised", "reference")

    def __init__(
        self,
        channels: int,
        latent: int,
        rel_dim: int = 2,
        abs_dim: int = 1,
        k: int = 20,
        n_freq: int = 5,
        hidden: int | None = None,
        groups: int | None = None,
        mode: str = "factorised",
    ) -> None:
        super().__init__()
        if mode not in self.MODES:
            raise ValueError(f"VCA mode must be one of {self.MODES}, got {mode!r}")
        self.channels, self.k, self.n_freq, self.mode = channels, k, n_freq, mode
        self.w_q = nn.Linear(latent, channels, bias=False)
        self.w_k_global = nn.Linear(latent, channels, bias=False)
        self.w_v_global = nn.Linear(latent, channels, bias=False)
        self.w_k = nn.Linear(channels, channels, bias=False)
        self.w_v = nn.Linear(channels, channels, bias=False)
        self.pos_embed = nn.Linear(fourier_size(rel_dim + abs_dim, n_freq), channels)
        self.mlp = _attention_mlp(channels, hidden or channels, groups or channels)
        rel, ab = relative_fourier_columns(rel_dim, abs_dim, n_freq)
        self.register_buffer("_rel_cols", torch.tensor(rel), persistent=False)
        self.register_buffer("_abs_cols", torch.tensor(ab), persistent=False)

    def prepare(
        self, latent: Tensor, features: Tensor, key_pos: Tensor, key_abs: Tensor
    ) -> dict[str, Tensor]:
        """Per-image terms shared by every pixel.

        Args:
            latent: global code, (B, latent).
            features: keypoint features, (B, N, C).
            key_pos: relative coordinates of the keypoints, (B, N, R).
            key_abs: per-keypoint offset part, (B, N, A).

        Returns:
            Tensors keyed by name (per keypoint: (B, N, .); per image: (B, .)).
        """
        q = self.w_q(latent)
        k_gl, v_gl = self.w_k_global(latent), self.w_v_global(latent)
        key, value = self.w_k(features), self.w_v(features)
        base = {"key_pos": key_pos, "key_abs": key_abs}
        if self.mode == "reference":
            return {**base, "query": q, "key": key, "value": value, "global_key": k_gl,
                    "global_value": v_gl}
        lin1, lin2 = self.mlp[0], self.mlp[2]
        w = self.pos_embed.weight
        p_abs = fourier_features(key_abs, self.n_freq) @ w[:, self._abs_cols].T + \
            self.pos_embed.bias  # (B, N, C)
        w_rel = w[:, self._rel_cols]
        return {
            **base,
            "hidden_key": lin1(q.unsqueeze(1) - key + p_abs),
            "value": value + p_abs,
            "global_logit": lin2(torch.relu(lin1(q - k_gl))),
            "global_value": v_gl,
            "w_pos_hidden": lin1.weight @ w_rel,
            "w_pos": w_rel,
        }

    def forward(self, prepared: dict[str, Tensor], query_pos: Tensor) -> Tensor:
        """Attend.

        Args:
            prepared: output of :meth:`prepare`.
            query_pos: relative coordinates of the query pixels, (B, Q, R).

        Returns:
            Shape (B, Q, C).
        """
        key_pos = prepared["key_pos"]
        idx = knn_indices(query_pos, key_pos, self.k)
        if self.mode == "reference":
            Q = query_pos.shape[1]
            nb = gather_neighbours(torch.cat([key_pos, prepared["key_abs"]], -1), idx)
            R = key_pos.shape[-1]
            delta = torch.cat([query_pos.unsqueeze(2) - nb[..., :R],
                               nb[..., R:].expand(-1, Q, -1, -1)], -1)
            return vector_cross_attention_reference(
                fourier_features(delta, self.n_freq), prepared["query"],
                gather_neighbours(prepared["key"], idx), gather_neighbours(prepared["value"], idx),
                prepared["global_key"], prepared["global_value"], self.pos_embed, self.mlp,
            )
        neighbours = None
        if idx is not None:
            neighbours = torch.zeros(*idx.shape[:2], key_pos.shape[1], dtype=torch.bool,
                                     device=idx.device).scatter_(-1, idx, True)
        lin2 = self.mlp[2]
        return vector_cross_attention(
            query_pos, key_pos, prepared["hidden_key"], prepared["value"],
            prepared["global_logit"], prepared["global_value"], prepared["w_pos_hidden"],
            lin2.weight, lin2.bias, prepared["w_pos"], self.n_freq, neighbours,
        )
