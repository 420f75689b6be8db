r"""The pose code refitted on fresh poses: what keypoints a geometry model can decode.

Inverse rendering (:mod:`netepu.geometry.inverse`) returns the keypoints decoded from the
code it finds, so the decoder's range is a floor under its error. The geometry stage trains
the encoder and the keypoint decoder (``decoder.mlp_pos``) by the keypoint loss alone, on the
poses of its training set (640 poses of one body). On fresh poses the shipped quadruped of
2026-11-26 decoded no closer than 60 mm, the biped 19 mm
(``docs/benchmarks/keypoint_floor.md``): the quadruped's keypoints from perfect masks were
~110 mm off.

:func:`refit_pose_code` trains those two parts again on a stream of fresh poses (keypoints
cost nothing to sample: no render), half of the model's own body and half of the synthetic
world's bodies (each individual its own proportions, ``proportion_variation``), while the
features the decoder hands the renderer stay those of the frozen model for the same pose:

.. math::
    L = \frac{1}{K}\sum_k \lVert \hat x_k(E(x)) - x_k \rVert
        + \beta\,\frac{\lVert f(E(x)) - f_0(E_0(x)) \rVert^2}{\lVert f_0(E_0(x)) \rVert^2}

with ``x`` the normalised keypoints (:func:`netepu.geometry.networks.normalise_keypoints`),
``E`` the encoder, :math:`\hat x` the keypoint decoder, ``f`` the decoded per-keypoint
features (the point-transformer blocks read the decoded positions, so they move a little), and
index 0 the model before. The feature decoder and the renderer are frozen: a pose's render
through its own code changes only as much as its features do.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from netepu.geometry.data import DataConfig
from netepu.geometry.model import GeometryModel
from netepu.geometry.networks import normalise_keypoints
from nsd.synth import make_individual
from nsd.synth.motion import sample_pose

__all__ = ["PoseCodeSettings", "fresh_poses", "refit_pose_code", "round_trip_error"]


@dataclass
class PoseCodeSettings:
    """Settings of :func:`refit_pose_code`.

    Attributes:
        steps: Adam steps (the learning rate falls to 0 on a cosine over them).
        lr: the starting learning rate (AdamW).
        batch: poses per step.
        pool: fresh poses drawn every ``renew`` steps (half of each kind of body), the batches
            drawn from them.
        renew: steps between new pools.
        feature_weight: :math:`\\beta`.
        proportion_variation: spread of the other bodies' proportions (the synthetic world's
            default, 1).
        seed: the stream of poses and the batches.
    """

    steps: int = 2400
    lr: float = 2e-3
    batch: int = 64
    pool: int = 128
    renew: int = 25
    feature_weight: float = 1.0
    proportion_variation: float = 1.0
    seed: int = 0


def fresh_poses(cfg: DataConfig, n: int, rng: np.random.Generator,
                proportion_variation: float = 0.0) -> Tensor:
    """``n`` world poses (n, K, 3) as the geometry data samples them (``pose_variation``,
    ``position_jitter``): of the model's own individual (``proportion_variation`` 0), or each of
    a new individual of the synthetic world with that spread of proportions."""
    def individual(identity: int):
        return make_individual(cfg.species, identity=identity, seed=cfg.seed,
                               proportion_variation=proportion_variation)

    own = None if proportion_variation else individual(cfg.identity)  # one body, built once
    out = []
    for _ in range(n):
        ind = own if own is not None else individual(int(rng.integers(2**31)))
        pos = rng.uniform(-cfg.position_jitter, cfg.position_jitter, 2)
        out.append(ind.keypoints3d(sample_pose(ind, rng, cfg.pose_variation,
                                               position=tuple(pos))).float())
    return torch.stack(out)


def round_trip_error(model: GeometryModel, poses: Tensor) -> Tensor:
    """Mean keypoint distance of ``poses`` (n, K, 3) encoded and decoded, (n,), scene units."""
    with torch.no_grad():
        return (model.encode(poses).keypoints - poses).norm(dim=-1).mean(1)


def refit_pose_code(model: GeometryModel, cfg: DataConfig, s: PoseCodeSettings | None = None,
                    progress: Callable[[int, float], None] | None = None) -> dict[str, float]:
    """Train ``model``'s encoder and keypoint decoder on fresh poses (module docstring), in
    place; every other parameter stays as it was, bit for bit.

    Args:
        model: a trained geometry model.
        cfg: the data it was trained on (its body and pose sampling).
        s: settings (default :class:`PoseCodeSettings`).
        progress: called with (step, loss) every 100 steps.

    Returns:
        the round trip (mm, mean over 200 held-out fresh poses of each kind of body) before and
        after, and the features' relative squared change on them.
    """
    s = s or PoseCodeSettings()
    rng = np.random.default_rng(s.seed)
    torch.manual_seed(s.seed)
    held = {kind: fresh_poses(cfg, 200, np.random.default_rng([s.seed, i]), spread)
            for i, (kind, spread) in enumerate((("own", 0.0),
                                                ("world", s.proportion_variation)))}
    before = {k: 1000 * float(round_trip_error(model, p).mean()) for k, p in held.items()}
    frozen = copy.deepcopy(model).eval()
    trained = [*model.encoder.parameters(), *model.decoder.mlp_pos.parameters()]
    flags = {p: p.requires_grad for p in model.parameters()}
    for p in model.parameters():
        p.requires_grad_(False)
    for p in trained:
        p.requires_grad_(True)
    opt = torch.optim.AdamW(trained, lr=s.lr)
    was_training = model.training
    model.eval()  # no dropout: the features are compared with the frozen model's
    half = s.pool // 2
    try:
        for step in range(s.steps):
            if step % s.renew == 0:
                pool = torch.cat([fresh_poses(cfg, half, rng),
                                  fresh_poses(cfg, s.pool - half, rng, s.proportion_variation)])
            for group in opt.param_groups:
                group["lr"] = s.lr * 0.5 * (1 + math.cos(math.pi * step / s.steps))
            x = pool[torch.from_numpy(rng.choice(len(pool), s.batch, replace=False))]
            norm, _ = normalise_keypoints(x, model.radius)
            pos, feats = model.decoder(model.encoder(norm))
            with torch.no_grad():
                _, target = frozen.decoder(frozen.encoder(norm))
            loss = (pos - norm).norm(dim=-1).mean() + s.feature_weight * (
                (feats - target).pow(2).mean() / target.pow(2).mean())
            opt.zero_grad()
            loss.backward()
            opt.step()
            if progress and (step + 1) % 100 == 0:
                progress(step + 1, float(loss.detach()))
    finally:
        for p, flag in flags.items():
            p.requires_grad_(flag)
        model.train(was_training)
    after = {k: 1000 * float(round_trip_error(model, p).mean()) for k, p in held.items()}
    with torch.no_grad():
        f = model.encode(held["own"]).features
        f0 = frozen.encode(held["own"]).features
    return {"round_trip_own_before_mm": before["own"], "round_trip_own_after_mm": after["own"],
            "round_trip_world_before_mm": before["world"],
            "round_trip_world_after_mm": after["world"],
            "feature_change": float((f - f0).pow(2).mean() / f0.pow(2).mean())}
