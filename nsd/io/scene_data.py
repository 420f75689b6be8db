"""Training data for NSD: a scene's frames at training resolution, view pairs.

Frames are decoded once (sequentially) into a file read through a memory map
(:class:`nsd.io.frame_store.FrameStore`: memory stays flat in the recording's length),
indexed as uint8 (T, V, 3, H, W); a batch is a set of random view pairs (t, v, w) of
the same instant with their median backgrounds and the relative rotation
:math:`R_{v \\to w}`. Sampling draws only from the ``numpy.random.Generator`` it is
given, so a training run resumes exactly.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nsd.cameras.calibration import CameraRig
from nsd.core.device import move
from nsd.core.errors import ConfigError
from nsd.core.memory import trim_heap
from nsd.cues.clustering import MixtureRules
from nsd.cues.count import footage_bodies
from nsd.cues.evidence import foreground_evidence
from nsd.cues.occupancy import multiview_proposals, scene_track, voxel_grid
from nsd.cues.proposals import evidence_proposals
from nsd.io.footage import MultiViewFootage
from nsd.io.frame_store import FrameStore, scratch_array
from nsd.priors.presence import smoothed_counts

__all__ = ["PairBatch", "SceneData", "split_frames"]


@dataclass
class PairBatch:
    """A batch of view pairs.

    Attributes:
        image_v, image_w: (B, 3, H, W) float in [0, 1].
        background_v, background_w: (B, 3, H, W).
        rotation_vw: :math:`R_{v \\to w}`, (B, 3, 3).
        frame, view_v, view_w: (B,) int64 indices.
        proposals_v, proposals_w: label-free window proposals (B, N, 4) (see
            :mod:`nsd.cues.proposals`), with validity (B, N), when computed; multi-view
            proposals (:mod:`nsd.cues.occupancy`) also carry camera-space depths (B, N)
            and share slots across views.
        count_v, count_w: (B,) the individuals in view per frame (the hull's count,
            smoothed over time, :func:`nsd.priors.presence.smoothed_counts`), when computed.
        owners_v, owners_w: (B, H, W) each pixel's hull individual (-1: none), with the
            multi-view proposals.
    """

    image_v: Tensor
    image_w: Tensor
    background_v: Tensor
    background_w: Tensor
    rotation_vw: Tensor
    frame: Tensor
    view_v: Tensor
    view_w: Tensor
    proposals_v: Tensor | None = None
    valid_v: Tensor | None = None
    proposals_w: Tensor | None = None
    valid_w: Tensor | None = None
    proposal_depth_v: Tensor | None = None
    proposal_depth_w: Tensor | None = None
    count_v: Tensor | None = None
    count_w: Tensor | None = None
    owners_v: Tensor | None = None
    owners_w: Tensor | None = None

    def to(self, device: torch.device | str) -> PairBatch:
        """The batch with every tensor on ``device`` (the model's, :mod:`nsd.core.device`)."""
        return move(self, device)


def split_frames(num_frames: int, val_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Training frames and held-out validation frames (the last ``val_fraction`` of the sequence).

    A contiguous tail is held out (not interleaved frames) so that validation
    poses are not near-duplicates of neighbouring training frames.
    """
    if not 0 <= val_fraction < 1:
        raise ConfigError(f"data.val_fraction must be in [0, 1), got {val_fraction}")
    n_val = round(num_frames * val_fraction)
    if num_frames - n_val < 1:
        raise ConfigError(f"data.val_fraction={val_fraction} leaves no training frames")
    idx = np.arange(num_frames)
    return idx[: num_frames - n_val], idx[num_frames - n_val :]


def to_float(images: Tensor) -> Tensor:
    """uint8 (..., 3, H, W) -> float32 in [0, 1]."""
    return images.float().div_(255.0)


class SceneData:
    """A scene folder's frames, backgrounds and rotations for training.

    Args:
        scene: scene folder.
        image_size: (width, height) of the training frames.
        cameras: subset of camera names (default: all).
        val_fraction: tail of the sequence held out for evaluation.
        max_frames: use only the first ``max_frames`` frames (0: all).
        units: the calibration file's length unit (:mod:`nsd.cameras.units`).
        frame_stride: keep every this many frames (hours of footage); indices ``t`` of
            this object are positions, footage frame :meth:`frame_index` ``(t)``.
        background: how cameras without a plate get their background
            (:data:`nsd.cues.background.BACKGROUND_METHODS`, ``data.background``).
        workers: processes decoding the frames and estimating the backgrounds, a camera
            each (0: one per available core; the run's ``threads`` where it sets them).
    """

    def __init__(
        self,
        scene: str | os.PathLike,
        image_size: Sequence[int] = (128, 128),
        cameras: Sequence[str] | None = None,
        val_fraction: float = 0.2,
        max_frames: int = 0,
        units: str = "auto",
        frame_stride: int = 1,
        background: str = "median",
        workers: int = 0,
    ) -> None:
        self.footage = MultiViewFootage(scene, cameras=cameras, image_size=tuple(image_size),
                                        units=units, background=background)
        stop = (
            self.footage.num_frames if max_frames <= 0 else min(max_frames, self.footage.num_frames)
        )
        self.frames = FrameStore(self.footage, stop, frame_stride, workers)  # (T, V, 3, H, W)
        self.frame_stride = int(frame_stride)
        bg = self.footage.background(workers=workers)
        self.backgrounds = to_float(torch.from_numpy(bg).permute(0, 3, 1, 2).contiguous())
        rig: CameraRig = self.footage.rig
        R = torch.as_tensor(np.stack([c.R for c in rig]), dtype=torch.float32)
        self.rotations = R.unsqueeze(0) @ R.unsqueeze(1).transpose(-1, -2)  # [v, w] = R_w R_v^T
        self.cameras = rig.stacked(torch.float32)  # K, R, t, dist per view (training size)
        self.train_frames, self.val_frames = split_frames(len(self.frames), val_fraction)
        self.proposals: Tensor | None = None
        self.proposal_valid: Tensor | None = None
        self.proposal_depths: Tensor | None = None
        self.counts: Tensor | None = None  # (T, V) individuals in view, see smooth_counts
        self.owners: Tensor | None = None  # (T, V, H, W) hull pixel owners (multi-view)

    def compute_multiview_proposals(
        self, k: int, threshold: float, softness: float, resolution: int = 48, split: bool = True,
        owners: bool = True, min_views: int | str = "auto", rules: MixtureRules | None = None,
    ) -> None:
        """Visual-hull proposals (boxes, depths, shared slots) for every frame (nsd.cues.occupancy);
        ``split``: see :func:`nsd.cues.clustering.cluster_individuals`; ``owners``: also keep
        every pixel's hull individual (``self.owners``, (T, V, H, W) int8, a third of the
        frames' size, on disk next to the frames: only the mask prior reads it); ``min_views``:
        :func:`nsd.cues.occupancy.hull_min_views`' setting; ``rules``: when the hull's 3D
        mixture replaces its k-means (None: the shipped defaults)."""

        grid = voxel_grid(self.rig, self.frame_hw, resolution, min_views=min_views,
                          key="prior_proposal.min_views")
        boxes, depths, valid = [], [], []
        T, V, _, H, W = self.frames.shape
        # (T, V, H, W) int8: hull individual, -1 none; on disk, as the frames
        pixel_owners = torch.from_numpy(
            scratch_array(self.frames.path.parent, (T, V, H, W), np.int8)
        ) if owners else None
        # the frames in order: each hull's Gaussians start the next's; the mixture tried or
        # not for the whole scene
        track = scene_track(lambda t: foreground_evidence(
            to_float(self.frames[t]), self.backgrounds, threshold, softness), range(T), grid, k,
            split, rules=rules)
        for t in range(T):
            ev = foreground_evidence(
                to_float(self.frames[t]), self.backgrounds, threshold, softness
            )
            b, d, ok, own, _ = multiview_proposals(ev, grid, k, split=split, track=track)
            boxes.append(b)
            depths.append(d)
            valid.append(ok)
            if pixel_owners is not None:
                pixel_owners[t] = own
        self.proposals, self.proposal_valid = torch.stack(boxes), torch.stack(valid)
        self.proposal_depths = torch.stack(depths)
        self.owners = pixel_owners
        trim_heap()  # the hull's temporaries, freed between the kept results

    def hull_bodies(self, threshold: float, softness: float, resolution: int,
                    min_views: int | str = "auto") -> tuple[int, np.ndarray]:
        """The separate bodies the visual hull shows in :data:`nsd.cues.count.SAMPLE` frames
        spread evenly over the scene (:func:`nsd.cues.count.scene_bodies`: a lower bound on
        the individuals, and the count of each frame); arguments as
        :meth:`compute_multiview_proposals`."""

        return footage_bodies(lambda t: foreground_evidence(
            to_float(self.frames[int(t)]), self.backgrounds, threshold, softness),
            self.frames.shape[0], self.rig, self.frame_hw, resolution, min_views)

    def smooth_counts(self, window: int, scene_population: bool = False) -> None:
        """Individuals in view per frame: the multi-view proposals' count, median over
        ``window`` frames (:func:`nsd.priors.presence.smoothed_counts`)."""

        if self.proposal_valid is None:
            raise ConfigError("counts need the multi-view proposals (compute them first)")
        self.counts = smoothed_counts(self.proposal_valid, window, scene_population)

    def compute_proposals(self, k: int, threshold: float, softness: float) -> None:
        """Single-view residual-evidence window proposals for every frame and view."""

        T, V = self.frames.shape[:2]
        boxes, valid = [], []
        chunk = max(1, 256 // V)
        for t0 in range(0, T, chunk):
            f = to_float(self.frames[t0 : t0 + chunk])  # (c, V, 3, H, W)
            ev = foreground_evidence(
                f.flatten(0, 1), self.backgrounds.repeat(len(f), 1, 1, 1), threshold, softness
            )
            b, ok = evidence_proposals(ev, k)
            boxes.append(b.view(len(f), V, k, 4))
            valid.append(ok.view(len(f), V, k))
        self.proposals, self.proposal_valid = torch.cat(boxes), torch.cat(valid)

    def frame_index(self, t: int) -> int:
        """The footage frame of position ``t`` (``t * frame_stride``)."""
        return int(t) * self.frame_stride

    @property
    def rig(self) -> CameraRig:
        return self.footage.rig

    @property
    def num_views(self) -> int:
        return self.frames.shape[1]

    @property
    def heldout_frames(self) -> np.ndarray:
        """Frames to evaluate on: the held-out tail, or every training frame when nothing is
        held out (``data.val_fraction=0``, e.g. a short real clip)."""
        return self.val_frames if len(self.val_frames) else self.train_frames

    @property
    def frame_hw(self) -> tuple[int, int]:
        """(H, W) of the training frames (the constructor's ``image_size`` is (W, H))."""
        return tuple(self.frames.shape[-2:])

    def pairs(self, t: np.ndarray, v: np.ndarray, w: np.ndarray) -> PairBatch:
        """The batch for given frame and view indices."""
        t_, v_, w_ = (torch.as_tensor(a, dtype=torch.long) for a in (t, v, w))
        batch = PairBatch(
            to_float(self.frames[t_, v_]),
            to_float(self.frames[t_, w_]),
            self.backgrounds[v_],
            self.backgrounds[w_],
            self.rotations[v_, w_],
            t_,
            v_,
            w_,
        )
        if self.proposals is not None:
            batch.proposals_v, batch.valid_v = self.proposals[t_, v_], self.proposal_valid[t_, v_]
            batch.proposals_w, batch.valid_w = self.proposals[t_, w_], self.proposal_valid[t_, w_]
        if self.proposal_depths is not None:
            batch.proposal_depth_v = self.proposal_depths[t_, v_]
            batch.proposal_depth_w = self.proposal_depths[t_, w_]
        if self.counts is not None:
            batch.count_v, batch.count_w = self.counts[t_, v_], self.counts[t_, w_]
        if self.owners is not None:
            batch.owners_v, batch.owners_w = self.owners[t_, v_].long(), self.owners[t_, w_].long()
        return batch

    def sample(
        self,
        rng: np.random.Generator,
        batch_size: int,
        frames: np.ndarray | None = None,
        same_view: float = 0.0,
    ) -> PairBatch:
        """Random view pairs of random training frames (``v != w``); with ``same_view`` > 0
        that share of the pairs, drawn at random, is a view with itself (``w = v``, a
        re-synthesis from its own windows, as the auto-encoder ablation does for all)."""
        if self.num_views < 2:
            raise ConfigError("Bi-NVS needs at least 2 cameras")
        if not 0 <= same_view <= 1:
            raise ConfigError(f"data.same_view must be in [0, 1], got {same_view}")
        pool = self.train_frames if frames is None else frames
        t = rng.choice(pool, size=batch_size)
        v = rng.integers(0, self.num_views, size=batch_size)
        w = (v + rng.integers(1, self.num_views, size=batch_size)) % self.num_views
        if same_view > 0:  # drawn only when asked, so the default draws are unchanged
            w = np.where(rng.random(batch_size) < same_view, v, w)
        return self.pairs(t, v, w)

    def views(self, t: int) -> tuple[Tensor, Tensor]:
        """All views of frame t and their backgrounds: (V, 3, H, W) each."""
        return to_float(self.frames[t]), self.backgrounds
