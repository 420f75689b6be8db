r"""Inverse rendering: multi-view silhouettes of one individual -> its 3D keypoints.

NePu's silhouette-to-keypoints (Giebenhain et al., ACCV 2022, sec. 4.3) with a
trained geometry model: find the global code ``z`` and translation ``c`` whose
decoded keypoints :math:`c + 2r\,\hat x(z)` render silhouettes that match the
observed ones in every view,

.. math::
    \min_{z, c}\ \frac{1}{V}\sum_v \mathrm{BCE}\big(\hat s_v(z, c), s_v\big)
    + \lambda_z \lVert z \rVert_2 .

The loss is evaluated at points per view and step: half straddling the
observed silhouette's boundary (:func:`netepu.geometry.sampling.sample_silhouette_points`),
half uniform over the observed silhouette's box enlarged by half its size.
As in full renders, a point outside the renderer's candidate region
(:func:`netepu.geometry.maps.candidate_region` of the current keypoints) is background.

Initialisation (the loss has local minima: a body seen from the side looks
alike facing left or right)
    ``c`` is the point closest to the viewing rays through the silhouettes'
    centroids (:func:`triangulate_centroids`). ``z`` starts from the codes of
    template poses (e.g. training poses) turned to ``headings`` directions
    about the world's up axis; all starts are optimised as one batch, the
    worse half is dropped every ``prune_every`` steps, and the best start wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from netepu.geometry.maps import BACKGROUND_LOGIT, candidate_region
from netepu.geometry.model import GeometryModel
from netepu.geometry.sampling import sample_silhouette_points
from nsd.cameras.batch import CameraBatch
from nsd.cameras.projection import pixel_to_normalized

__all__ = [
    "InverseResult",
    "InverseSettings",
    "invert_silhouettes",
    "rotate_about_up",
    "triangulate_centroids",
]


@dataclass
class InverseSettings:
    """Settings of :func:`invert_silhouettes` (every field is a config value).

    Attributes:
        steps: Adam steps.
        lr: Adam learning rate of ``z`` in units of the codes' RMS entry (the
            translation uses ``lr * radius``).
        points_per_view: loss points per view and step.
        headings: start directions per template.
        prune_every: steps between dropping the worse half of the starts (0: never).
        latent_weight: :math:`\\lambda_z` (the training prior's weight).
        sigma_near: spread of the near-boundary points, pixels.
        margin: candidate-region margin (the renderer's), body radii.
        up: world up axis.
    """

    steps: int = 120
    lr: float = 0.05
    points_per_view: int = 384
    headings: int = 4
    prune_every: int = 25
    latent_weight: float = 0.0625
    sigma_near: float = 1.5
    margin: float = 0.35
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass
class InverseResult:
    """Recovered individual.

    Attributes:
        keypoints: decoded world keypoints, (K, 3).
        z: global code, (d_z,).
        centre: translation, (3,).
        loss: final silhouette loss of the chosen start.
        start_losses: final loss of every start alive at the end, (S,).
    """

    keypoints: Tensor
    z: Tensor
    centre: Tensor
    loss: float
    start_losses: Tensor


def triangulate_centroids(masks: Tensor, camera: CameraBatch) -> Tensor:
    """Least-squares point closest to the viewing rays through the silhouettes' centroids.

    Args:
        masks: silhouettes, (V, H, W) bool, V >= 2 (one view: the point on its
            ray at the distance of the world origin).
        camera: ``K, R, t`` (and ``dist``) with batch V.

    Returns:
        World point, (3,) float64.
    """
    V, H, W = masks.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    m = masks.double()
    n = m.flatten(1).sum(1).clamp(min=1)
    uv = torch.stack([(m * xs).flatten(1).sum(1) / n, (m * ys).flatten(1).sum(1) / n], -1)
    camera = CameraBatch.from_mapping(camera)
    K, R, t = (x.double() for x in (camera.K, camera.R, camera.t))
    dist = camera.dist
    xy = pixel_to_normalized(uv[:, None], K, None if dist is None else dist.double())[:, 0]
    d_cam = torch.cat([xy, torch.ones(V, 1, dtype=torch.float64)], -1)
    d = (R.transpose(-1, -2) @ d_cam[..., None])[..., 0]
    d = d / d.norm(dim=-1, keepdim=True)
    o = -(R.transpose(-1, -2) @ t[..., None])[..., 0]  # camera centres
    if V == 1:
        return o[0] + d[0] * o[0].norm()
    P = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]  # (V, 3, 3)
    return torch.linalg.solve(P.sum(0), (P @ o[..., None]).sum(0))[:, 0]


def rotate_about_up(points: Tensor, angle: float, up: Tensor) -> Tensor:
    """Rotate points (..., 3) by ``angle`` radians about the unit axis ``up`` through the origin."""
    u = up / up.norm()
    c, s = math.cos(angle), math.sin(angle)
    cross = torch.cross(u.expand_as(points), points, dim=-1)
    return points * c + cross * s + u * (points @ u)[..., None] * (1 - c)


def _points(masks: np.ndarray, n: int, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """Loss points per view: half near the boundary, half in the enlarged silhouette box."""
    V, H, W = masks.shape
    out = []
    for v in range(V):
        ys, xs = np.nonzero(masks[v])
        x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
        ex, ey = (x1 - x0) // 2 + 2, (y1 - y0) // 2 + 2
        box = np.zeros((H, W), bool)
        box[max(0, y0 - ey):y1 + ey + 1, max(0, x0 - ex):x1 + ex + 1] = True
        uv, _ = sample_silhouette_points(masks[v], n // 2, n - n // 2, rng, sigma, box)
        out.append(uv)
    return np.stack(out)


def _optimise(model, masks, camera, templates, s: InverseSettings, rng):
    """The batched multi-start optimisation; returns z (S, d_z), centre (S, 3), losses (S,)."""
    V, H, W = masks.shape
    up = torch.tensor(s.up, dtype=torch.float32)
    centre0 = triangulate_centroids(masks, camera).float()
    starts = []
    for tpl in templates.float():
        centred = tpl - tpl.mean(0)
        for h in range(s.headings):
            starts.append(rotate_about_up(centred, 2 * math.pi * h / s.headings, up))
    with torch.no_grad():
        z0 = model.encode(torch.stack(starts) + centre0).z
    sigma = z0.pow(2).mean().sqrt().clamp(min=1e-8)
    w = (z0 / sigma).requires_grad_(True)  # z = sigma w
    centre = centre0.expand(len(starts), 3).clone().requires_grad_(True)

    def adam(w: Tensor, centre: Tensor) -> torch.optim.Adam:
        return torch.optim.Adam([{"params": [w], "lr": s.lr},
                                 {"params": [centre], "lr": s.lr * model.radius}])

    opt = adam(w, centre)
    np_masks = masks.numpy()
    cams = CameraBatch.from_mapping(camera).to(torch.float32)
    losses = torch.zeros(len(starts))
    for step in range(s.steps):
        S = w.shape[0]
        z = sigma * w
        uv = torch.from_numpy(_points(np_masks, s.points_per_view, rng, s.sigma_near))
        px, py = uv[..., 0].long(), uv[..., 1].long()
        label = masks[torch.arange(V)[:, None], py, px].float()
        code = model.decode(z, centre)
        rep = cams.repeat(S)
        ctx = model.renderer.prepare(code.keypoints.repeat_interleave(V, 0),
                                     code.features.repeat_interleave(V, 0),
                                     code.z.repeat_interleave(V, 0), rep)
        logit = model.query(ctx, uv.repeat(S, 1, 1))["logit"]  # (S V, P)
        with torch.no_grad():
            inside = torch.stack([torch.from_numpy(candidate_region(
                ctx.frame.uv[b], float(ctx.frame.scale[b]), s.margin, (W, H)))[
                py[b % V], px[b % V]] for b in range(S * V)])
        logit = torch.where(inside, logit, torch.full_like(logit, BACKGROUND_LOGIT))
        bce = F.binary_cross_entropy_with_logits(logit, label.repeat(S, 1), reduction="none")
        per_start = bce.mean(1).reshape(S, V).mean(1)
        opt.zero_grad()
        (per_start + s.latent_weight * z.norm(dim=-1)).sum().backward()
        opt.step()
        losses = per_start.detach()
        if s.prune_every and (step + 1) % s.prune_every == 0 and S > 1:
            keep = losses.argsort()[: max(1, S // 2)]
            state = opt.state_dict()["state"]
            w = w.detach()[keep].requires_grad_(True)
            centre = centre.detach()[keep].requires_grad_(True)
            opt = adam(w, centre)
            for i, param in enumerate((w, centre)):  # carry Adam's moments of the survivors
                if i in state:
                    opt.state[param] = {k: (v[keep] if torch.is_tensor(v) and v.dim() else v)
                                        for k, v in state[i].items()}
            losses = losses[keep]
    return (sigma * w).detach(), centre.detach(), losses


def invert_silhouettes(
    model: GeometryModel,
    masks: Tensor,
    camera: CameraBatch,
    templates: Tensor,
    settings: InverseSettings | None = None,
    rng: np.random.Generator | None = None,
) -> InverseResult:
    """Recover the keypoints of one individual from its silhouettes in V calibrated views.

    Args:
        model: trained geometry model (kept frozen).
        masks: observed silhouettes, (V, H, W) bool, each non-empty.
        camera: ``K, R, t, dist`` with batch V.
        templates: template poses (T, K, 3) world keypoints (only their shape
            matters: they are centred and turned).
        settings: see :class:`InverseSettings`.
        rng: generator of the loss points (default seeded 0).

    Returns:
        :class:`InverseResult`.
    """
    s = settings or InverseSettings()
    rng = rng or np.random.default_rng(0)
    if not bool(masks.flatten(1).any(1).all()):
        raise ValueError("invert_silhouettes: every view needs a non-empty silhouette")
    flags = [p.requires_grad for p in model.parameters()]
    for p in model.parameters():
        p.requires_grad_(False)
    try:
        z, centre, losses = _optimise(model, masks, camera, templates, s, rng)
        best = int(losses.argmin())
        with torch.no_grad():
            code = model.decode(z[best:best + 1], centre[best:best + 1])
    finally:
        for p, flag in zip(model.parameters(), flags, strict=True):
            p.requires_grad_(flag)
    return InverseResult(code.keypoints[0], z[best], centre[best], float(losses[best]), losses)
