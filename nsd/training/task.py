"""The NSD training task: Bi-NVS re-synthesis with weak priors, per step (:class:`NSDTask`).

Stages (NSD supplement A): with ``model.depth_from_step > 0`` the first steps
train B, E and D with the additive compositor (stage 1), then E and D are
re-initialised (``model.reinit_at_depth``) and the depth compositor is turned
on (stage 2). ``stage=pose`` trains the pose regressor P on the frozen latent
(stage 3, see :mod:`nsd.training.pose_task`).

Loss per view pair (both directions of Bi-NVS):

* image loss: residual-weighted pixel MSE + ``ssim_weight`` x (1 - SSIM);
* foreground-evidence prior: the composited coverage 1 - T(inf) should match
  the background-residual evidence (a label-free cue from the median background);
* weak priors on the windows of both views (position, scale, aspect) and the
  presence prior;
* with ``prior_presence.target=marginal``, the presence learns a detached,
  label-free target, each window's marginal contribution to explaining the
  foreground evidence (:mod:`nsd.priors.presence`); with ``target=hull``, in each frame
  and view the windows ranked first by presence are on, as many as the
  label-free visual hull finds individuals (:mod:`nsd.cues.occupancy`), and the
  proposal prior matches those individuals to the windows that are on.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from nsd.core import distributed
from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.cues.evidence import foreground_evidence
from nsd.cues.proposals import match_proposals
from nsd.cues.triangulation import triangulate_midpoints, window_rays
from nsd.evaluation.decomposition import evaluate_model
from nsd.evaluation.visualise import training_grid
from nsd.inference.multiview import InferenceSettings
from nsd.io.scene_data import SceneData
from nsd.model.association import appearance_similarity, association_softmax, exclude_absent
from nsd.model.build import build_model
from nsd.priors.depth import depth_prior
from nsd.priors.mask import hull_mask_prior
from nsd.priors.presence import (
    marginal_presence_target,
    presence_target_loss,
    ranked_presence_target,
    window_area,
)
from nsd.priors.proposal import association_prior, proposal_prior
from nsd.priors.window import aspect_prior, position_prior, presence_prior, scale_prior
from nsd.training.losses import total_image_loss
from nsd.training.window_count import settle_window_count

__all__ = ["NSDTask"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AdamConfig(ConfigSection):
    """NSD's Adam with a learning rate per network (the ``optim`` group, ``conf/optim/``)."""

    APP: ClassVar[str] = "train"  # defaults: conf/train.yaml, section `optim`
    KEY: ClassVar[str] = "optim"

    lr_detector: float
    lr_encoder: float
    lr_decoder: float
    weight_decay: float

    def validate(self) -> None:
        """Finite, positive rates (a NaN rate turns every weight NaN within a step)."""
        for key in ("lr_detector", "lr_encoder", "lr_decoder"):
            value = getattr(self, key)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(f"optim.{key} must be a finite number > 0, got {value!r}")
        wd = self.weight_decay
        if not isinstance(wd, (int, float)) or not math.isfinite(wd) or wd < 0:
            raise ConfigError(f"optim.weight_decay must be a finite number >= 0, got {wd!r}")


def _reset(module: nn.Module) -> None:
    for m in module.modules():
        if hasattr(m, "reset_parameters") and m is not module:
            m.reset_parameters()


class NSDTask:
    """Bi-NVS training on a scene (implements nsd.core.trainer.TrainTask)."""

    def __init__(
        self, cfg: DictConfig, data: SceneData, gt: Any = None, device: torch.device | None = None
    ) -> None:
        self.cfg, self.data, self.gt = cfg, data, gt
        self.device = torch.device("cpu") if device is None else device
        declared = len(gt.scene.individuals) if gt is not None else None
        settle_window_count(cfg, data, declared, data.footage.scene.name)  # before the networks
        self.cameras = data.cameras.to(self.device)
        self.model = build_model(OmegaConf.to_container(cfg.model, resolve=True)).to(self.device)
        self.depth_from = int(cfg.model.depth_from_step)
        self.reinit = bool(cfg.model.reinit_at_depth)
        self.use_depth = bool(cfg.model.depth)
        self._make_optimizer()
        self.stage2_started = self.depth_from <= 0
        self.step = 0
        self.presence_target = str(cfg.prior_presence.target)
        self.presence_normalise = str(cfg.prior_presence.normalise)
        self.presence_cap = str(cfg.prior_presence.cap)
        self.association_prior_score = str(cfg.prior_association.score)
        self._check_prior_settings()
        self._prepare_proposals(data)

    def _check_prior_settings(self) -> None:
        """The prior settings NSDTask reads, checked before any work (errors name the key)."""
        if self.presence_normalise not in ("mask", "box"):
            raise ConfigError(
                f"prior_presence.normalise must be 'mask' or 'box', got {self.presence_normalise!r}"
            )
        if self.presence_cap not in ("none", "proposals"):
            raise ConfigError(
                f"prior_presence.cap must be 'none' or 'proposals', got {self.presence_cap!r}"
            )
        if self.presence_cap == "proposals" and self.cfg.prior_proposal.source != "multiview":
            raise ConfigError(
                "prior_presence.cap=proposals needs prior_proposal.source=multiview (the "
                "visual hull's individuals are the cap)"
            )
        if self.presence_target not in ("none", "marginal", "hull"):
            raise ConfigError(
                "prior_presence.target must be 'none', 'marginal' or 'hull', got "
                f"{self.presence_target!r}"
            )
        if self.cfg.prior_mask.weight > 0 and self.cfg.prior_proposal.source != "multiview":
            raise ConfigError(
                "prior_mask=hull needs prior_proposal.source=multiview (the visual hull's "
                "pixel owners are its target)"
            )
        if self.presence_target == "hull" and self.cfg.prior_proposal.source != "multiview":
            raise ConfigError(
                "prior_presence.target=hull needs prior_proposal.source=multiview (the visual "
                "hull's individuals say how many windows are on)"
            )
        if self.association_prior_score not in ("appearance", "full"):
            raise ConfigError(
                "prior_association.score must be 'appearance' or 'full', got "
                f"{self.association_prior_score!r}"
            )

    def _prepare_proposals(self, data: SceneData) -> None:
        """The label-free proposals (and hull counts) that the configured priors need."""
        cfg = self.cfg
        pp = cfg.prior_proposal
        if (
            pp.weight > 0
            or cfg.prior_association.weight > 0
            or cfg.prior_mask.weight > 0
            or cfg.prior_depth.source == "proposals"
            or self.presence_target == "hull"  # the hull's count is the presence target
        ):
            args = (cfg.model.num_windows, cfg.loss.evidence_threshold, cfg.loss.evidence_softness)
            if pp.source == "multiview":
                split = pp.split
                if split not in ("auto", True, False):
                    raise ConfigError(
                        f"prior_proposal.split must be auto, true or false, got {split!r}"
                    )
                if split == "auto":  # num_windows is an upper bound when presence is learned
                    split = not cfg.model.detector.presence
                data.compute_multiview_proposals(*args, resolution=pp.resolution, split=split,
                                                 owners=cfg.prior_mask.weight > 0,
                                                 min_views=pp.min_views,
                                                 rules=InferenceSettings.from_config(
                                                     cfg.get("inference")).mixture)
                if self.presence_target == "hull":
                    self._hull_counts(cfg.prior_presence, data)
            elif pp.source == "single_view":
                data.compute_proposals(*args)
            else:
                raise ConfigError(
                    f"prior_proposal.source must be 'multiview' or 'single_view' when proposal, "
                    f"association or proposal-depth priors are on, got {pp.source!r}"
                )

    @staticmethod
    def _hull_counts(pp: DictConfig, data: SceneData) -> None:
        """The presence target's count per frame and view (``prior_presence.count_*``)."""
        window = pp.count_window
        population = pp.count_population
        if population not in ("frame", "scene"):
            raise ConfigError(
                f"prior_presence.count_population must be 'frame' or 'scene', got {population!r}"
            )
        try:
            if not isinstance(window, int):
                raise ValueError(f"got {window!r}")
            data.smooth_counts(window, population == "scene")
        except ValueError as e:
            raise ConfigError(f"prior_presence.count_window: {e}") from None

    def _make_optimizer(self) -> None:
        o = AdamConfig.from_config(OmegaConf.to_container(self.cfg.optim, resolve=True))
        m = self.model
        groups = [
            {"params": m.detector.parameters(), "lr": o.lr_detector},
            {"params": m.encoder.parameters(), "lr": o.lr_encoder},
            {"params": m.decoder.parameters(), "lr": o.lr_decoder},
        ]
        if m.refiner is not None:  # the mask refiner learns at the decoder's rate
            groups.append({"params": m.refiner.parameters(), "lr": o.lr_decoder})
        self.opt = torch.optim.Adam(
            groups,
            weight_decay=o.weight_decay,
            fused=self.device.type in ("cpu", "cuda"),  # one kernel: 3x faster on CPU
        )

    # ------------------------------------------------------------ TrainTask
    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"adam": self.opt}

    def extra_state(self) -> dict[str, Any]:
        return {
            "stage2_started": self.stage2_started,
            "cameras": list(self.data.rig.names),
            "image_size": list(self.data.frame_hw),
            "scene": str(self.data.footage.scene),
        }

    def load_extra_state(self, state: Mapping[str, Any]) -> None:
        self.stage2_started = bool(state.get("stage2_started", self.stage2_started))
        self.model.cfg.depth = self.use_depth and self.stage2_started

    def _update_presence(self, step: int) -> None:
        """Presence is 1 (not learned, its prior constant) before ``prior_presence.from_step``.

        Learned from the first step, presence collapsed to ~0 in every window (the
        early, blurry renderings reconstruct worse than the median background, and a
        low presence also scales down the gradients that would improve them;
        docs/benchmarks/count.md), so the decomposition forms first.
        """
        want = bool(self.cfg.model.detector.presence)
        start = int(self.cfg.prior_presence.from_step)
        self.model.detector.use_presence = want and step >= start

    def _update_stage(self, step: int) -> None:
        if not self.stage2_started and step >= self.depth_from:
            self.stage2_started = True
            if self.reinit:
                _reset(self.model.encoder)
                _reset(self.model.decoder)
                # the ranks' random streams differ: every replica takes rank 0's new weights
                distributed.broadcast_parameters([self.model.encoder, self.model.decoder])
                self._make_optimizer()
            log.info("step %d: stage 2 (depth compositor on)", step)
        self.model.cfg.depth = self.use_depth and self.stage2_started

    def losses(self, batch) -> dict[str, torch.Tensor]:
        """Every loss term of a batch of view pairs by name; ``loss`` is their weighted sum.

        Terms (weights in :meth:`term_weights`): ``pixel`` and ``ssim`` (re-synthesis of
        both views), ``foreground`` (coverage vs. evidence), the window priors
        ``prior_position``, ``prior_scale``, ``prior_aspect``, ``prior_presence``, and
        where configured ``presence_target``, ``prior_proposal``, the marginal presence
        target, ``prior_depth`` and ``prior_association``.
        """
        cams = self.cameras
        rv, rw, wv, ww = self.model(
            batch.image_v,
            batch.image_w,
            batch.background_v,
            batch.background_w,
            batch.rotation_vw,
            cams[batch.view_v],
            cams[batch.view_w],
        )
        evidence = self._evidence(batch)
        out = self._image_terms(batch, rv, rw, evidence)
        boxes = torch.cat([wv.det.boxes, ww.det.boxes])
        out.update(self._window_priors(boxes, wv, ww, batch.image_v.shape[-2:]))
        valid = None if batch.valid_v is None else torch.cat([batch.valid_v, batch.valid_w])
        active = self._hull_presence_term(batch, wv, ww, out)
        matching = self._proposal_term(batch, boxes, valid, active, out)
        if self.presence_target == "marginal" and self.model.detector.use_presence:
            caps = (None, None)
            if self.presence_cap == "proposals":
                caps = (batch.valid_v.sum(-1), batch.valid_w.sum(-1))
            H, W = batch.image_v.shape[-2:]
            out.update(self._presence_target(evidence, rv, rw, wv, ww, (H, W), caps))
        if self.cfg.prior_depth.weight > 0:
            out["prior_depth"] = self._depth_term(batch, rv, rw, wv, ww, matching, valid)
        if self.cfg.prior_association.weight > 0 and batch.proposal_depth_v is not None:
            out["prior_association"] = self._association_term(batch, rv, rw, wv, ww, matching)
        if self.cfg.prior_mask.weight > 0:
            out["prior_mask"] = self._mask_term(batch, rv, rw, matching, valid)
        weights = self.term_weights()
        total = torch.zeros((), device=self.device)
        for k, v in out.items():
            total = total + weights[k] * v
        out["loss"] = total
        return out

    def term_weights(self) -> dict[str, float]:
        """The weight of every named loss term (config values; the proposal prior anneals)."""
        c = self.cfg
        return {
            "pixel": 1.0,
            "ssim": c.loss.ssim_weight,
            "foreground": c.loss.foreground_weight,
            "prior_position": c.prior_position.weight,
            "prior_scale": c.prior_scale.weight,
            "prior_aspect": c.prior_aspect.weight,
            "prior_presence": c.prior_presence.weight,
            "presence_target": c.prior_presence.target_weight,
            "presence_target_on": 0.0,  # logged only: windows on per view in the target
            "prior_proposal": self.proposal_weight(),
            "prior_depth": c.prior_depth.weight,
            "prior_association": c.prior_association.weight,
            "prior_mask": c.prior_mask.weight,
        }

    def _evidence(self, batch) -> list[torch.Tensor]:
        """Foreground evidence (B, H, W) of both views of the pairs."""
        c = self.cfg.loss
        pairs = ((batch.image_v, batch.background_v), (batch.image_w, batch.background_w))
        return [
            foreground_evidence(img, bg, c.evidence_threshold, c.evidence_softness)
            for img, bg in pairs
        ]

    def _image_terms(self, batch, rv, rw, evidence) -> dict[str, torch.Tensor]:
        """``pixel``, ``ssim`` and ``foreground``, averaged over both directions of Bi-NVS."""
        c = self.cfg.loss
        # both views in one batch: one structural loss of 2B images instead of two of B
        ev = torch.cat(evidence)
        weight = 1 + c.residual_weight * ev if c.residual_weight > 0 else None
        out = total_image_loss(
            torch.cat([rv.image, rw.image]), torch.cat([batch.image_v, batch.image_w]), weight,
            c.ssim_weight, c.ssim_window, c.renormalise, parts=2,
        )
        if c.foreground_weight > 0:
            background = torch.cat([rv.composite.background_weight, rw.composite.background_weight])
            out["foreground"] = (1 - background - ev).pow(2).mean()
        return out

    def _window_priors(self, boxes, wv, ww, size) -> dict[str, torch.Tensor]:
        """The weak priors on the windows of both views (NSD: position, scale, aspect)."""
        c = self.cfg
        return {
            "prior_position": position_prior(boxes),
            "prior_scale": scale_prior(boxes, c.prior_scale.target),
            "prior_aspect": aspect_prior(boxes, c.prior_aspect.ratio, tuple(size)),
            "prior_presence": presence_prior(torch.cat([wv.det.presence, ww.det.presence])),
        }

    def _hull_presence_term(self, batch, wv, ww, out: dict) -> torch.Tensor | None:
        """With ``prior_presence.target=hull``: adds ``presence_target`` and returns the
        windows that are on (as many per view as the hull counts individuals)."""
        if not (self.presence_target == "hull" and self.model.detector.use_presence):
            return None
        presence = torch.cat([wv.det.presence, ww.det.presence])
        count = torch.cat([batch.count_v, batch.count_w])  # NSDTask._hull_counts
        hull_target = ranked_presence_target(presence, count)
        out["presence_target"] = presence_target_loss(presence, hull_target)
        out["presence_target_on"] = hull_target.sum(-1).mean()
        return hull_target > 0.5

    def _proposal_term(self, batch, boxes, valid, active, out: dict) -> torch.Tensor | None:
        """Adds ``prior_proposal`` where the batch has proposals; returns the matching."""
        if batch.proposals_v is None:
            return None
        props = torch.cat([batch.proposals_v, batch.proposals_w])
        matching = match_proposals(boxes, props, valid, active)
        out["prior_proposal"] = proposal_prior(boxes, props, valid, matching)
        return matching

    def _mask_term(self, batch, rv, rw, matching, valid) -> torch.Tensor:
        """``prior_mask``: each window's composited mask against its hull individual's pixels."""
        if batch.owners_v is None or matching is None:
            raise ConfigError("prior_mask needs prior_proposal=multiview (the hull's pixel owners)")
        weights = torch.cat([rv.composite.weights, rw.composite.weights])
        owners = torch.cat([batch.owners_v, batch.owners_w])
        return hull_mask_prior(weights, owners, matching, valid)

    def _depth_term(self, batch, rv, rw, wv, ww, matching, valid) -> torch.Tensor:
        """``prior_depth`` from the multi-view proposals' depths or from triangulation."""
        c = self.cfg.prior_depth
        if c.source == "proposals" and batch.proposal_depth_v is not None:
            target = torch.cat([batch.proposal_depth_v, batch.proposal_depth_w])
            depths = torch.cat([wv.det.depths, ww.det.depths])
            return depth_prior(
                depths, target.gather(1, matching), valid.gather(1, matching), c.unit
            )
        if c.source == "triangulation":
            return self._depth_prior(batch, rv, rw, wv, ww)
        raise ConfigError(
            f"prior_depth.source {c.source!r} needs multi-view proposals"
            if c.source == "proposals"
            else f"prior_depth.source must be 'proposals' or 'triangulation', got {c.source!r}"
        )

    def _association_term(self, batch, rv, rw, wv, ww, matching) -> torch.Tensor:
        """``prior_association`` in both directions of the pair."""
        B = batch.image_v.shape[0]
        mv, mw = matching[:B], matching[B:]
        av, aw = self._prior_associations(rv, rw, wv, ww)
        return (
            association_prior(av, mv, batch.valid_v, mw, batch.valid_w)
            + association_prior(aw, mw, batch.valid_w, mv, batch.valid_v)
        ) / 2

    def _prior_associations(self, rv, rw, wv, ww) -> tuple[torch.Tensor, torch.Tensor]:
        """The soft associations (B, N, N) the association prior pulls on, for v and w.

        ``prior_association.score=appearance``: the appearance-only softmax (eq. 4-5), the
        part of the score the networks can change. ``full``: the association used for
        re-synthesis, whose detached ray-distance term can contradict the proposals by far
        more than the appearances can make up: its cross-entropy then stays large (up to
        ~14 measured) and only pushes the encoder around (docs/nsd.md).
        """
        m = self.model.cfg
        if self.association_prior_score == "full" or not (m.association and m.mode == "bi_nvs"):
            return rv.association, rw.association
        sim = appearance_similarity(wv.app, ww.app, m.association_dims)
        present = self.model.present
        return (
            association_softmax(exclude_absent(sim, present(ww)), m.association_beta),
            association_softmax(exclude_absent(sim.mT, present(wv)), m.association_beta),
        )

    def _presence_target(self, evidence, rv, rw, wv, ww, size, caps) -> dict[str, torch.Tensor]:
        """BCE of both views' presences against their marginal-gain targets (nsd.priors.presence);
        ``evidence``: the two views' foreground evidence (B, H, W), ``size``: (H, W),
        ``caps``: per view (B,) the most windows that may be on, or None."""
        pp = self.cfg.prior_presence
        loss, on = torch.zeros((), device=self.device), torch.zeros((), device=self.device)
        for r, win, ev, cap in ((rv, wv, evidence[0], caps[0]), (rw, ww, evidence[1], caps[1])):
            if self.presence_normalise == "box":
                area = window_area(win.det.boxes, size)
            else:  # the window's own (ungated) mask area, at least min_area pixels
                area = r.ungated_masks.flatten(2).sum(-1).clamp_min(pp.min_area)
            target, _ = marginal_presence_target(
                r.ungated_masks, ev, area, pp.margin, win.det.presence, cap
            )
            loss = loss + presence_target_loss(win.det.presence, target) / 2
            on = on + target.sum(-1).mean() / 2
        return {"presence_target": loss, "presence_target_on": on}

    def _depth_prior(self, batch, rv, rw, wv, ww) -> torch.Tensor:
        """Triangulated relative-depth consistency for both directions (nsd.cues.triangulation)."""
        cams = self.cameras
        H, W = batch.image_v.shape[-2:]
        total = torch.zeros((), device=self.device)
        for r, tgt, src, vt, vs in (
            (rv, wv, ww, batch.view_v, batch.view_w),
            (rw, ww, wv, batch.view_w, batch.view_v),
        ):
            o_t, d_t = window_rays(
                tgt.det.boxes, cams.K[vt], cams.R[vt], cams.t[vt], cams.dist[vt], (H, W)
            )
            o_s, d_s = window_rays(
                src.det.boxes, cams.K[vs], cams.R[vs], cams.t[vs], cams.dist[vs], (H, W)
            )
            partner = r.association.argmax(-1)  # target slot j <- source window
            d_s = d_s.gather(1, partner[..., None].expand(-1, -1, 3))
            points, ok = triangulate_midpoints(o_t, d_t.detach(), o_s, d_s.detach())
            depth = (points @ cams.R[vt].transpose(-1, -2) + cams.t[vt][:, None])[..., 2]
            ok = ok & (tgt.det.presence > 0.5)
            total = total + depth_prior(tgt.det.depths, depth, ok, self.cfg.prior_depth.unit) / 2
        return total

    def proposal_weight(self) -> float:
        """The proposal prior's weight, annealed linearly to 0 over ``decay_steps``."""
        p = self.cfg.prior_proposal
        if p.decay_steps <= 0:
            return float(p.weight)
        return float(p.weight) * max(0.0, 1.0 - self.step / p.decay_steps)

    def training_step(self, step: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
        self.step = step
        self._update_stage(step)
        self._update_presence(step)
        same = float(self.cfg.data.same_view)
        batch = self.data.sample(rng, self.cfg.batch_size, same_view=same)
        return self.losses(batch.to(self.device))

    def evaluate(self, step: int) -> dict[str, float]:
        """Metrics with the configured inference; with ground truth and multi-view
        inference, also NSD's single-image inference (prefixed ``single_``)."""
        settings = InferenceSettings.from_config(self.cfg.inference)
        runs = [("", settings)]
        if settings.multiview and self.gt is not None:
            runs.append(("single_", dataclasses.replace(settings, views="single")))
        sets = [("", _spread(self.data.heldout_frames, self.cfg.eval_frames))]
        if self.cfg.eval_train_frames > 0:
            sets.append(("train_", _spread(self.data.train_frames, self.cfg.eval_train_frames)))
        metrics = {}
        for where, frames in sets:
            for how, s in runs:
                m = evaluate_model(self.model, self.data, frames, self.gt, inference=s)
                metrics.update({f"{where}{how}{k}": v for k, v in m.items()})
        return metrics

    def image_grids(self, step: int) -> dict[str, np.ndarray]:
        frames = _spread(self.data.heldout_frames, 3)
        return {"nsd": training_grid(self.model, self.data, frames)}


def _spread(frames: np.ndarray, n: int) -> np.ndarray:
    """n frames spread evenly over ``frames``."""
    if len(frames) <= n:
        return np.asarray(frames)
    return np.asarray(frames)[np.linspace(0, len(frames) - 1, n).round().astype(int)]
