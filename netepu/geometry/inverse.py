r"""Inverse rendering: multi-view silhouettes of one individual -> its 3D keypoints.

NePu's silhouette-to-keypoints (Giebenhain et al., ACCV 2022, sec. 4.3) with a
trained geometry model: find the global code ``z`` and translation ``c`` whose
decoded keypoints :math:`c + 2r\,\hat x(z)` render silhouettes that match the
observed ones in every view,

.. math::
    \min_{z, c}\ \frac{1}{V}\sum_v \frac{\sum_p w_{vp}\,\mathrm{BCE}\big(\hat s_v(z, c)_p,
    s_{vp}\big)}{\sum_p w_{vp}} + \lambda_z \lVert z \rVert_2 ,
    \qquad w_{vp} = 1 - o_{vp}\,(1 - s_{vp}) .

Occluders ``o`` (other subjects' visible masks, optional) make the loss occlusion-aware:
where another subject covers a pixel, the observed mask cannot say whether this
subject is there behind it, so a background label there is not a constraint (weight 0);
the subject's own visible pixels always count.

The loss is evaluated at points per view and step: half straddling the
observed silhouette's boundary (:func:`netepu.geometry.sampling.sample_silhouette_points`),
half uniform over the observed silhouette's box enlarged by half its size. While many
starts are alive their step is spent on telling them apart, not on fine detail: the points
per view of a step are ``point_budget`` shared among the ``S`` starts alive, between a
quarter of ``points_per_view`` and all of it (:func:`points_per_step`).
As in full renders, a point outside the renderer's candidate region
(:func:`netepu.geometry.maps.candidate_region` of the current keypoints) is background.

Initialisation (the loss has local minima: a body seen from the side looks
alike facing left or right, and a limb far from its place is not pulled back)
    ``c`` is the point closest to the viewing rays through the silhouettes'
    centroids (:func:`triangulate_centroids`). ``z`` starts from the codes of
    template poses (e.g. poses of the model's own synthetic individual) turned to
    ``headings`` directions about the world's up axis. Where there are more of
    these candidates than ``screen_keep``, each is scored once, without gradients,
    by the loss at ``screen_points`` points per view (the same points for all),
    and the ``screen_keep`` lowest are kept: a library of poses is cheap to score
    and puts the starts near the observed pose. The kept starts are optimised as
    one batch, the worse half is dropped every ``prune_every`` steps, and the best
    start wins.

A learned initialiser (:mod:`netepu.geometry.initialiser`)
    predicts the keypoints from the subject's visual hull; their code and centre are one
    start. ``init_templates`` screened template starts (the first ``init_poses`` templates at
    ``init_headings`` headings each, scored at ``init_screen_points``, loss points shared as
    ``init_point_budget``, at most ``init_points_per_view`` each) run beside it
    for ``init_steps`` steps, the worse half dropped after half of them (``init_turns`` > 1
    adds the learned start turned about the up axis).

Warm starts (a subject followed over frames)
    Given the result of an earlier frame (``warm``), one start from its code, its
    translation moved by the change of the triangulated centroid, runs ``warm_steps``
    steps. If its loss ends above ``warm_tolerance`` times the earlier frame's loss
    (a fast turn, a wrong earlier fit), the cold multi-start runs as well and the
    lower loss wins.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from netepu.geometry.initialiser import PoseInitialiser, initial_keypoints
from netepu.geometry.losses import occlusion_aware_silhouette_loss
from netepu.geometry.maps import BACKGROUND_LOGIT, candidate_region
from netepu.geometry.model import GeometryModel
from netepu.geometry.sampling import sample_silhouette_points
from nsd.cameras.batch import CameraBatch
from nsd.cameras.projection import pixel_to_normalized
from nsd.core.errors import ConfigError

__all__ = [
    "InverseResult",
    "InverseSettings",
    "invert_silhouettes",
    "points_per_step",
    "rotate_about_up",
    "triangulate_centroids",
]

_SCREEN_CHUNK = 32  # candidates scored at a time by the screening


@dataclass
class InverseSettings:
    """Settings of :func:`invert_silhouettes` (every field is a config value).

    Attributes:
        steps: Adam steps.
        lr: Adam learning rate of ``z`` in units of the codes' RMS entry (the
            translation uses ``lr * radius``).
        points_per_view: loss points per view and step, at most.
        point_budget: loss points per view summed over the starts alive: a step of S starts
            uses ``point_budget // S`` points per view, clamped to a quarter of
            ``points_per_view`` and all of it (0: ``points_per_view`` always).
        headings: start directions per template.
        prune_every: steps between dropping the worse half of the starts (0: never).
        screen_keep: candidates (templates x headings) kept for the optimisation after
            scoring them once; 0, or no more candidates than this: no screening.
        screen_points: loss points per view of the screening.
        latent_weight: :math:`\\lambda_z` (the training prior's weight).
        sigma_near: spread of the near-boundary points, pixels.
        margin: candidate-region margin (the renderer's), body radii.
        up: world up axis.
        warm_steps: Adam steps of a warm start.
        warm_tolerance: a warm start whose loss ends above this many times the earlier
            frame's loss is checked against the cold multi-start.
        warm_lr: ``lr`` of a warm start (Adam's steps are about ``lr`` per code entry
            whatever the gradient, so a long warm chain random-walks at a high rate).
        init_steps: Adam steps of the one start a learned initialiser gives.
        init_templates: screened template starts optimised beside it (0: none); with more
            than one start the worse half is dropped after ``init_prune`` steps.
        init_prune: steps after which the worse half of the starts beside a learned one is
            dropped (and again every as many steps while more than one is left; 0: half of
            ``init_steps``).
        init_turns: the learned start at this many headings about the up axis through its
            centre (1: as predicted; 2: also turned 180 degrees, the heading a silhouette tells
            worst), all optimised.
        init_poses: the first this many templates are screened beside a learned start (0: all).
        init_headings, init_screen_points, init_point_budget, init_points_per_view:
            ``headings``, ``screen_points``, ``point_budget`` and ``points_per_view`` beside a
            learned start (its templates only stand in where it
            is wrong, so they are screened more coarsely than the templates alone).
    """

    steps: int = 120
    lr: float = 0.05
    points_per_view: int = 384
    point_budget: int = 768
    headings: int = 8
    prune_every: int = 25
    screen_keep: int = 8
    screen_points: int = 128
    latent_weight: float = 0.0625
    sigma_near: float = 1.5
    margin: float = 0.35
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    warm_steps: int = 40
    warm_tolerance: float = 1.25
    warm_lr: float = 0.05
    init_steps: int = 40
    init_templates: int = 2
    init_prune: int = 0
    init_poses: int = 8
    init_turns: int = 1
    init_headings: int = 4
    init_screen_points: int = 64
    init_point_budget: int = 576
    init_points_per_view: int = 288

    def __post_init__(self) -> None:
        """Counts are whole numbers >= 0 (those that pick points or directions >= 1), rates
        and weights >= 0, the learning rates > 0.

        Raises:
            ConfigError: naming the field and its value.
        """
        at_least_one = {"points_per_view", "headings", "screen_points", "init_turns",
                        "init_headings", "init_screen_points", "init_points_per_view"}
        for name, value in vars(self).items():
            if name == "up":
                continue
            least = 1 if name in at_least_one else 0
            whole = isinstance(getattr(type(self), name), int)
            number = isinstance(value, numbers.Real) and not isinstance(value, bool)
            if not (number and value >= least  # NaN, a word or None fail here
                    and (not whole or (math.isfinite(value) and int(value) == value))):
                raise ConfigError(f"keypoints inverse setting {name}: "
                                  f"{'a whole number ' if whole else 'a number '}>= {least}, "
                                  f"got {value!r}")
        up = self.up
        if (not isinstance(up, (tuple, list)) or len(up) != 3
                or not all(isinstance(v, numbers.Real) and math.isfinite(v) for v in up)
                or not any(v != 0 for v in up)):
            raise ConfigError(f"keypoints inverse setting up: three finite numbers, not all "
                              f"zero, got {up!r}")
        if self.lr <= 0 or self.warm_lr <= 0:
            raise ConfigError(f"keypoints inverse settings lr and warm_lr: > 0, got {self.lr}, "
                              f"{self.warm_lr}")


@dataclass
class InverseResult:
    """Recovered individual.

    Attributes:
        keypoints: decoded world keypoints, (K, 3).
        z: global code, (d_z,).
        centre: translation, (3,).
        loss: final silhouette loss of the chosen start.
        start_losses: final loss of every start alive at the end, (S,).
        anchor: the triangulated centroid of the silhouettes, (3,) (warm starts move
            the translation by its change).
        history: loss of the best start alive after each step, (steps,).
        warm: the result comes from the warm start.
        start_steps: Adam steps summed over starts (the work done).
    """

    keypoints: Tensor
    z: Tensor
    centre: Tensor
    loss: float
    start_losses: Tensor
    anchor: Tensor
    history: Tensor
    warm: bool = False
    start_steps: int = 0


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


def points_per_step(s: InverseSettings, starts: int) -> int:
    """Loss points per view of an optimisation step with ``starts`` starts alive
    (:attr:`InverseSettings.point_budget`)."""
    if s.point_budget <= 0:
        return s.points_per_view
    return min(s.points_per_view, max(s.points_per_view // 4, s.point_budget // max(1, starts)))


def _regions(masks: np.ndarray, ignored: np.ndarray) -> np.ndarray:
    """Where a view's uniform loss points fall: the silhouette's box enlarged by half its
    size, without the ignored pixels, (V, H, W) bool."""
    V, H, W = masks.shape
    out = np.zeros((V, H, W), bool)
    for v in range(V):
        ys, xs = np.nonzero(masks[v])
        x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
        ex, ey = (x1 - x0) // 2 + 2, (y1 - y0) // 2 + 2
        out[v, max(0, y0 - ey):y1 + ey + 1, max(0, x0 - ex):x1 + ex + 1] = True
    return out & ~ignored


def _points(masks: np.ndarray, regions: np.ndarray, n: int, rng: np.random.Generator,
            sigma: float) -> np.ndarray:
    """Loss points per view, (V, n, 2): half near the boundary, half in the view's region."""
    return np.stack([sample_silhouette_points(m, n // 2, n - n // 2, rng, sigma, r)[0]
                     for m, r in zip(masks, regions, strict=True)])


def _code_starts(model, masks, camera, templates, s: InverseSettings, anchor, warm,
                 learned=None):
    """Starting codes (S, d_z) and translations (S, 3): the templates turned to every
    heading at the anchor, the earlier frame's fit moved with the anchor, or the learned
    initialiser's keypoints ``learned`` (K, 3)."""
    if warm is not None:
        return warm.z[None].float(), (warm.centre + anchor - warm.anchor)[None].float()
    up = torch.tensor(s.up, dtype=torch.float32)
    if learned is not None:
        centre = learned.float().mean(0)
        with torch.no_grad():
            code = model.encode(_turned(learned.float(), max(1, s.init_turns), up) + centre)
        return code.z.float(), code.centre.float()
    starts = torch.cat([_turned(tpl, s.headings, up) for tpl in templates.float()])
    with torch.no_grad():
        z0 = model.encode(starts + anchor).z
    return z0, anchor.expand(len(starts), 3).clone()


def _turned(pose: Tensor, turns: int, up: Tensor) -> Tensor:
    """``pose`` (K, 3) centred on its centroid and turned to ``turns`` headings evenly about
    ``up``, (turns, K, 3)."""
    centred = pose - pose.mean(0)
    return torch.stack([rotate_about_up(centred, 2 * math.pi * h / turns, up)
                        for h in range(turns)])


def _start_losses(model, z, centre, cams, masks, ignored, uv, margin) -> Tensor:
    """The module docstring's silhouette loss of each start, (S,), differentiable.

    Args: codes ``z`` (S, d_z) at ``centre`` (S, 3); the views ``cams`` (batch V), their
    observed ``masks`` and ``ignored`` pixels (V, H, W) bool; the points ``uv`` (V, P, 2).
    """
    S = z.shape[0]
    V, H, W = masks.shape
    px, py = uv[..., 0].long(), uv[..., 1].long()
    rows = torch.arange(V)[:, None]
    label, skip = masks[rows, py, px].float(), ignored[rows, py, px]
    code = model.decode(z, centre)
    ctx = model.renderer.prepare(code.keypoints.repeat_interleave(V, 0),
                                 code.features.repeat_interleave(V, 0),
                                 code.z.repeat_interleave(V, 0), cams.repeat(S))
    logit = model.query(ctx, uv.repeat(S, 1, 1), ("logit",))["logit"]  # (S V, P)
    with torch.no_grad():
        inside = torch.stack([torch.from_numpy(candidate_region(
            ctx.frame.uv[b], float(ctx.frame.scale[b]), margin, (W, H)))[
            py[b % V], px[b % V]] for b in range(S * V)])
    logit = torch.where(inside, logit, torch.full_like(logit, BACKGROUND_LOGIT))
    per_view = occlusion_aware_silhouette_loss(logit, label.repeat(S, 1), skip.repeat(S, 1))
    return per_view.reshape(S, V).mean(1)


@torch.no_grad()
def _screen(model, masks, cams, regions, z0, centre0, s: InverseSettings, rng, ignored,
            keep: int | None = None):
    """The ``keep`` (default ``screen_keep``) starts of lowest loss at one draw of
    ``screen_points`` points per view (module docstring), all of them where there are no
    more."""
    keep = s.screen_keep if keep is None else keep
    if not keep or len(z0) <= keep:
        return z0, centre0
    uv = torch.from_numpy(_points(masks.numpy(), regions, s.screen_points, rng, s.sigma_near))
    losses = torch.cat([
        _start_losses(model, z0[i:i + _SCREEN_CHUNK], centre0[i:i + _SCREEN_CHUNK], cams, masks,
                      ignored, uv, s.margin) for i in range(0, len(z0), _SCREEN_CHUNK)])
    best = losses.argsort()[:keep]
    return z0[best], centre0[best]


def _optimise(model, masks, cams, regions, z0, centre0, steps, s: InverseSettings, rng, ignored,
              lr):
    """The batched multi-start optimisation from codes ``z0`` (S, d_z) at ``centre0`` (S, 3)
    in the views ``cams`` (float32, batch V), loss points uniform in ``regions``; returns
    z (S', d_z), centre (S', 3), losses (S',), the best loss per step (steps,) and the
    start-steps done."""
    sigma = z0.pow(2).mean().sqrt().clamp(min=1e-8)
    w = (z0 / sigma).requires_grad_(True)  # z = sigma w
    centre = centre0.clone().requires_grad_(True)

    def adam(w: Tensor, centre: Tensor) -> torch.optim.Adam:
        return torch.optim.Adam([{"params": [w], "lr": lr},
                                 {"params": [centre], "lr": lr * model.radius}])

    opt = adam(w, centre)
    np_masks = masks.numpy()
    losses = torch.zeros(len(z0))
    history, work = [], 0
    for step in range(steps):
        S = w.shape[0]
        work += S
        z = sigma * w
        uv = torch.from_numpy(_points(np_masks, regions, points_per_step(s, S), rng,
                                      s.sigma_near))
        per_start = _start_losses(model, z, centre, cams, masks, ignored, uv, s.margin)
        opt.zero_grad()
        (per_start + s.latent_weight * z.norm(dim=-1)).sum().backward()
        opt.step()
        losses = per_start.detach()
        history.append(float(losses.min()))
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
    return (sigma * w).detach(), centre.detach(), losses, torch.tensor(history), work


def invert_silhouettes(
    model: GeometryModel,
    masks: Tensor,
    camera: CameraBatch,
    templates: Tensor,
    settings: InverseSettings | None = None,
    rng: np.random.Generator | None = None,
    occluders: Tensor | None = None,
    warm: InverseResult | None = None,
    initialiser: PoseInitialiser | None = None,
    start_pose: Tensor | None = None,
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
        occluders: other subjects' visible masks, (V, H, W) bool: background labels there
            are ignored (the module docstring's :math:`o`).
        warm: this individual's result at an earlier frame: start from it (module docstring).
        initialiser: a learned initialiser: a cold start is its prediction (and
            ``init_templates`` screened templates) refined ``init_steps`` steps instead of the
            ``screen_keep`` screened templates for ``steps`` (module docstring).
        start_pose: world keypoints (K, 3) that stand in for a learned initialiser's
            prediction, refined as it would be (e.g. an earlier fit turned about the up
            axis, :mod:`netepu.pipeline.heading`).

    Returns:
        :class:`InverseResult`.
    """
    s = settings or InverseSettings()
    rng = rng or np.random.default_rng(0)
    masks = masks.bool()
    if not bool(masks.flatten(1).any(1).all()):
        raise ValueError("invert_silhouettes: every view needs a non-empty silhouette")
    if occluders is not None and occluders.shape != masks.shape:
        raise ValueError(f"invert_silhouettes: occluders {tuple(occluders.shape)} and masks "
                         f"{tuple(masks.shape)} differ")
    ignored = torch.zeros(masks.shape, dtype=torch.bool) if occluders is None else (
        occluders.bool() & ~masks)
    anchor = triangulate_centroids(masks, camera).float()
    cams = CameraBatch.from_mapping(camera).to(torch.float32)
    regions = _regions(masks.numpy(), ignored.numpy())  # where uniform loss points fall
    flags = [p.requires_grad for p in model.parameters()]
    for p in model.parameters():
        p.requires_grad_(False)

    if start_pose is not None:
        learned = start_pose.float()
    elif initialiser is not None:
        learned = initial_keypoints(initialiser, masks, ignored, camera, anchor)
    else:
        learned = None

    def run(start: InverseResult | None, steps: int) -> tuple:
        run_s = s
        z0, c0 = _code_starts(model, masks, camera, templates, s, anchor, start, learned)
        if start is None and learned is None:
            z0, c0 = _screen(model, masks, cams, regions, z0, c0, s, rng, ignored)
        elif start is None:
            steps = s.init_steps
            run_s = replace(s, prune_every=s.init_prune or max(1, steps // 2),
                            headings=s.init_headings,
                            screen_points=s.init_screen_points,
                            point_budget=s.init_point_budget,
                            points_per_view=s.init_points_per_view)
            if s.init_templates:
                pool = templates[:s.init_poses] if s.init_poses else templates
                zt, ct = _code_starts(model, masks, camera, pool, run_s, anchor, None)
                zt, ct = _screen(model, masks, cams, regions, zt, ct, run_s, rng, ignored,
                                 s.init_templates)
                z0, c0 = torch.cat([z0, zt]), torch.cat([c0, ct])
        lr = s.warm_lr if start is not None else s.lr
        return _optimise(model, masks, cams, regions, z0, c0, steps, run_s, rng, ignored, lr)

    try:
        z, centre, losses, history, work = run(warm, s.warm_steps if warm else s.steps)
        from_warm = warm is not None
        if from_warm and float(losses.min()) > s.warm_tolerance * warm.loss:
            cold = run(None, s.steps)
            work += cold[4]
            if float(cold[2].min()) < float(losses.min()):
                z, centre, losses, history, _ = cold
                from_warm = False
        best = int(losses.argmin())
        with torch.no_grad():
            code = model.decode(z[best:best + 1], centre[best:best + 1])
    finally:
        for p, flag in zip(model.parameters(), flags, strict=True):
            p.requires_grad_(flag)
    return InverseResult(code.keypoints[0], z[best], centre[best], float(losses[best]), losses,
                         anchor, history, from_warm, work)
