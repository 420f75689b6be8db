r"""Multi-view inference: each frame's detector windows fused with the visual hull of its cameras.

NSD's detector sees one image at a time. When all calibrated views of an instant are
decomposed together, the label-free visual hull of their background residuals
(:mod:`nsd.cues.occupancy`, the proposals that already guide training) says where each
individual stands, which window of every view shows it and how far it is from each
camera. In each view (:func:`fuse_detections`):

* every detector window is matched to a hull individual
  (:func:`nsd.cues.proposals.match_proposals`);
* a matched window moves towards the individual's projection by ``window_blend``
  :math:`a`: centre :math:`t = (1 - a)\, t_{det} + a\, t_{hull}`, half-size
  :math:`s = s_{det}^{1 - a} s_{hull}^{a}`;
* with ``depth="hull"`` the windows take their individuals' camera-space depths, when every
  window of the view has one (the two sources' depths have different units, so a view
  never mixes them); otherwise the view keeps the detector's depths;
* the individual of each window (its *slot*, shared by all views) joins the cross-view
  association: windows of two views on the same individual get ``slot_bonus`` added to
  their association score (:func:`nsd.inference.association_scores.association_scores`).

NSD then crops, encodes, decodes, composites and refines with the fused windows
(:func:`nsd.inference.single.decompose`): the masks, their ownership, the appearance and the
latent stay the learned model's. ``views="single"`` is NSD's own single-image inference.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig
from torch import Tensor

from nsd.cameras.calibration import CameraRig
from nsd.core.config import ConfigSection
from nsd.core.device import model_device, move
from nsd.core.errors import ConfigError
from nsd.cues.clustering import ClusterTrack, MixtureRules
from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence
from nsd.cues.holes import Speckle
from nsd.cues.occupancy import (
    CONTEST_BAND,
    VoxelGrid,
    hull_individuals,
    multiview_proposals,
    scene_track,
    voxel_grid,
)
from nsd.cues.proposals import match_proposals
from nsd.inference.colour_models import ColourModels
from nsd.inference.neighbours import NeighbourAgreement
from nsd.inference.single import Decomposition, decompose
from nsd.model.bi_nvs import BiNVS
from nsd.model.detector import Detections

__all__ = ["InferenceSettings", "carry_hull_track", "decompose_views", "fuse_detections",
           "window_candidates", "window_owners"]

VIEWS = ("multiview", "single")
DEPTHS = ("hull", "detector")


@dataclass(frozen=True)
class InferenceSettings(ConfigSection):
    """How frames are decomposed at inference (the ``inference`` block of eval and export).

    Attributes:
        views: ``multiview`` (fuse with the visual hull of all cameras) or ``single``
            (each image alone, as NSD).
        window_blend: how far a window moves towards its hull individual (0: the
            detector's window, 1: the hull's).
        depth: ``hull`` (the individuals' camera-space depths) or ``detector``.
        slot_bonus: association score added for two windows on the same individual.
        resolution: voxels per side of the hull's grid.
        min_views: cameras that must see a voxel of the hull (``auto``: a majority,
            :func:`nsd.cues.occupancy.hull_min_views`).
        colour_sigma: colour agreement of the mask ownership
            (:func:`nsd.inference.single.ownership`).
        hull_ownership: log-score bonus of the window whose hull individual owns a pixel
            (:func:`nsd.cues.occupancy.owned_pixels`) in the mask ownership (0: the
            learned ownership alone).
        hull_contested: that bonus where the hull cannot settle the owner, on pixels near
            two or more individuals (:func:`nsd.cues.occupancy.contested_pixels`).
        hole_share: the holes a visible mask encloses, up to this share of its area, are
            filled (:func:`nsd.cues.holes.fill_holes`; 0: off).
        island_share: a subject's islands enclosed by one other subject, up to this share
            of its area, are given to that subject (:func:`nsd.cues.holes.give_islands`;
            0: off).
        neighbour_weight, neighbour_sigma: the Potts term by which neighbouring pixels of one
            colour share an owner (:class:`nsd.inference.neighbours.NeighbourAgreement`,
            :attr:`neighbours`; weight 0: off).
        colour_model, colour_model_bins, colour_model_margin, colour_model_separation: the
            individuals' colour models in the mask ownership
            (:class:`nsd.inference.colour_models.ColourModels`, :attr:`colour_models`;
            weight 0: off).
        mixture_gain, mixture_slack, mixture_scene_gain, mixture_scene_sample: when the
            hull's 3D mixture replaces its k-means (:class:`nsd.cues.clustering.MixtureRules`,
            :attr:`mixture`).
    """

    APP: ClassVar[str] = "train"  # defaults: conf/train.yaml, section `inference`
    KEY: ClassVar[str] = "inference"

    views: str
    window_blend: float
    depth: str
    slot_bonus: float
    resolution: int
    min_views: int | str
    colour_sigma: float
    hull_ownership: float
    hull_contested: float
    hole_share: float
    island_share: float
    neighbour_weight: float
    neighbour_sigma: float
    colour_model: float
    colour_model_bins: int
    colour_model_margin: float
    colour_model_separation: float
    mixture_gain: float
    mixture_slack: float
    mixture_scene_gain: float
    mixture_scene_sample: int

    def validate(self) -> None:
        def need(ok: bool, key: str, what: str) -> None:
            if not ok:
                raise ConfigError(f"inference.{key} {what}, got {getattr(self, key)!r}")

        need(self.views in VIEWS, "views", f"must be one of {VIEWS}")
        need(0.0 <= float(self.window_blend) <= 1.0, "window_blend", "must be in [0, 1]")
        need(self.depth in DEPTHS, "depth", f"must be one of {DEPTHS}")
        need(float(self.slot_bonus) >= 0.0, "slot_bonus", "must be >= 0")
        need(int(self.resolution) >= 8, "resolution", "must be >= 8 voxels")
        need(self.min_views == "auto" or (isinstance(self.min_views, int)
                                          and not isinstance(self.min_views, bool)
                                          and self.min_views >= 2),
             "min_views", "must be auto or a number of cameras >= 2")
        need(float(self.colour_sigma) >= 0.0, "colour_sigma", "must be >= 0 (0: off)")
        need(float(self.hull_ownership) >= 0.0, "hull_ownership", "must be >= 0 (0: off)")
        need(float(self.hull_contested) >= 0.0, "hull_contested", "must be >= 0 (0: off)")
        for key in ("hole_share", "island_share"):
            share = getattr(self, key)
            need(isinstance(share, (int, float)) and not isinstance(share, bool)
                 and 0.0 <= float(share) <= 1.0, key,
                 "must be a share of a mask's area in [0, 1] (0: off)")
        for key in ("neighbour_weight", "neighbour_sigma"):
            value = getattr(self, key)
            need(isinstance(value, (int, float)) and not isinstance(value, bool)
                 and 0.0 <= float(value) < float("inf"), key, "must be a number >= 0")
        need(float(self.neighbour_sigma) > 0.0 or float(self.neighbour_weight) == 0.0,
             "neighbour_sigma", "must be > 0 while inference.neighbour_weight is on")
        need(float(self.colour_model) >= 0.0, "colour_model", "must be >= 0 (0: off)")
        bins = self.colour_model_bins
        need(isinstance(bins, int) and not isinstance(bins, bool) and 2 <= bins <= 32,
             "colour_model_bins",
             "must be a whole number of levels per colour channel in [2, 32]")
        need(float(self.colour_model_margin) >= 0.0, "colour_model_margin", "must be >= 0")
        need(isinstance(self.colour_model_separation, (int, float))
             and not isinstance(self.colour_model_separation, bool)
             and 0.0 <= float(self.colour_model_separation) <= 1.0, "colour_model_separation",
             "must be a kappa in [0, 1] (0: the colour models everywhere)")
        self.mixture  # noqa: B018  (validates the mixture_* keys)

    @classmethod
    def from_config(cls, node: DictConfig | Mapping[str, Any] | None) -> InferenceSettings:
        """Settings from an ``inference`` block: the shipped defaults with the block's values
        (a block may give only some keys; None: the defaults). Unknown keys are an error."""
        items = dict(node or {})
        unknown = sorted(set(items) - set(cls.__dataclass_fields__))
        if unknown:
            raise ConfigError(f"inference has no setting {unknown[0]!r}")
        return cls.defaults(**items)

    @property
    def mixture(self) -> MixtureRules:
        """The hull's :class:`nsd.cues.clustering.MixtureRules` from the ``mixture_*`` keys."""
        return MixtureRules.from_config(
            {f.name: getattr(self, f.name) for f in dataclasses.fields(MixtureRules)})

    @property
    def speckle(self) -> Speckle:
        """The masks' :class:`nsd.cues.holes.Speckle` rules from ``hole_share`` and
        ``island_share``."""
        return Speckle(float(self.hole_share), float(self.island_share))

    @property
    def neighbours(self) -> NeighbourAgreement:
        """The masks' :class:`nsd.inference.neighbours.NeighbourAgreement` from
        ``neighbour_weight`` and ``neighbour_sigma``."""
        return NeighbourAgreement(float(self.neighbour_weight), float(self.neighbour_sigma))

    @property
    def colour_models(self) -> ColourModels | None:
        """The individuals' colour models of the mask ownership, None where the weight is 0."""
        if float(self.colour_model) <= 0:
            return None
        return ColourModels(float(self.colour_model), int(self.colour_model_bins),
                            float(self.colour_model_margin),
                            float(self.colour_model_separation))

    @property
    def multiview(self) -> bool:
        return self.views == "multiview"

    def for_views(self, num_views: int) -> InferenceSettings:
        """These settings for footage of ``num_views`` cameras: single-image inference when
        there is only one (nothing to fuse), else unchanged."""
        return self if num_views >= 2 else dataclasses.replace(self, views="single")

    def grid(self, rig: CameraRig, image_size: tuple[int, int]) -> VoxelGrid:
        """The hull's voxel grid for cameras ``rig`` scaled to frames of ``image_size`` (H, W)."""
        if len(rig) < 2:
            raise ConfigError(
                "inference.views=multiview needs at least 2 cameras; use inference.views=single"
            )
        return voxel_grid(rig, tuple(image_size), int(self.resolution),
                          min_views=self.min_views, key="inference.min_views")


def fuse_detections(
    det: Detections,
    proposals: Tensor,
    proposal_depths: Tensor,
    valid: Tensor,
    blend: float,
    depth: str = "hull",
) -> tuple[Detections, Tensor]:
    """Move detector windows towards their matched hull individuals (module docstring).

    Args:
        det: the detector's windows of V views (boxes (V, N, 4), depths and presence (V, N)).
        proposals: the hull individuals' windows (V, N, 4); slot j is one individual.
        proposal_depths: their camera-space depths (V, N).
        valid: (V, N) bool.
        blend: ``window_blend`` in [0, 1].
        depth: ``hull`` or ``detector``.

    Returns:
        the fused detections and the slot of each window (V, N), -1 where none is valid.
    """
    match = match_proposals(det.boxes, proposals, valid, det.presence >= 0.5)
    target = proposals.gather(1, match[..., None].expand(-1, -1, 4))
    ok = valid.gather(1, match)
    scale = det.boxes[..., :2].log().lerp(target[..., :2].log(), blend).exp()
    centre = det.boxes[..., 2:].lerp(target[..., 2:], blend)
    boxes = torch.where(ok[..., None], torch.cat([scale, centre], -1), det.boxes)
    depths = det.depths
    if depth == "hull":
        whole = ok.all(-1, keepdim=True)  # a view never mixes the two depth units
        depths = torch.where(whole, proposal_depths.gather(1, match), det.depths)
    slots = torch.where(ok, match, torch.full_like(match, -1))
    return Detections(boxes, depths, det.presence), slots


def window_owners(owners: Tensor, slots: Tensor) -> Tensor:
    """The hull's pixel owners as windows: (V, H, W) slot ids and each window's slot (V, N)
    (-1: none) -> (V, H, W) window index, -1 where no window holds the pixel's slot."""
    out = torch.full_like(owners, -1)
    for v in range(owners.shape[0]):
        for n, s in enumerate(slots[v].tolist()):
            if s >= 0:
                out[v][owners[v] == s] = n
    return out


def window_candidates(candidates: Tensor, slots: Tensor, contested: Tensor) -> Tensor:
    """(V, k, H, W) hull individuals near each pixel and each window's slot (V, N) ->
    (V, N, H, W): the windows that may own each pixel (all of them where it is not
    contested)."""
    H, W = candidates.shape[-2:]
    index = slots.clamp_min(0)[..., None, None].expand(-1, -1, H, W)
    near = candidates.gather(1, index) & (slots >= 0)[..., None, None]
    return near | ~contested[:, None]


def _hull_split(model: BiNVS) -> bool:
    """The hull's ``split`` for this model: the count is known unless windows have a
    presence (as training's ``prior_proposal.split=auto``)."""
    return not model.detector.use_presence


def model_scene_track(
    model: BiNVS,
    views: Callable[[int], tuple[Tensor, Tensor]],
    instants: Sequence[int],
    grid: VoxelGrid,
    rules: MixtureRules | None = None,
) -> ClusterTrack:
    """The hull's :class:`ClusterTrack` for ``model``'s windows through a scene's
    ``instants`` (:func:`nsd.cues.occupancy.scene_track`: the mixture tried or not for the
    whole scene, by ``rules``, e.g. :attr:`InferenceSettings.mixture`; None: the shipped
    defaults); ``views(t)`` gives an instant's images and backgrounds (V, 3, H, W)."""
    def evidence(t: int) -> Tensor:
        return foreground_evidence(*views(t), EVIDENCE_THRESHOLD, EVIDENCE_SOFTNESS)

    return scene_track(evidence, instants, grid, model.cfg.num_windows, split=_hull_split(model),
                       rules=rules)


@torch.inference_mode()
def carry_hull_track(
    model: BiNVS,
    images: Tensor,
    backgrounds: Tensor,
    num_views: int,
    grid: VoxelGrid,
    track: ClusterTrack,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
) -> list[tuple[Tensor, Tensor]]:
    """The hull's voxels and individuals of T instants of V views (T * V, 3, H, W), one
    (indices, labels) pair per instant (:func:`nsd.cues.occupancy.hull_individuals`), with
    ``track`` moved on through them: what :func:`decompose_views` computes first, done
    apart, so that one process carries the track through a sequence and others decompose
    its instants from these labels (``clusters``)."""
    ev = foreground_evidence(images, backgrounds, evidence_threshold, evidence_softness)
    return [hull_individuals(ev[s : s + num_views], grid, model.cfg.num_windows,
                             split=_hull_split(model), track=track)
            for s in range(0, images.shape[0], num_views)]


@torch.inference_mode()
def decompose_views(
    model: BiNVS,
    images: Tensor,
    backgrounds: Tensor,
    num_views: int,
    settings: InferenceSettings,
    grid: VoxelGrid | None = None,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
    track: ClusterTrack | None = None,
    clusters: list[tuple[Tensor, Tensor]] | None = None,
    **kwargs,
) -> Decomposition:
    """Decompose T instants of V calibrated views, (T * V, 3, H, W) instant-major.

    With ``settings.views == "single"`` every image is decomposed alone; otherwise each
    instant's windows are fused with the visual hull of its V views (``grid`` from
    :meth:`InferenceSettings.grid`). The hull's clustering runs through the T instants in
    order (:class:`nsd.cues.clustering.ClusterTrack`): from ``track`` where given (a caller
    going through a sequence call by call), afresh otherwise; or each instant's hull
    individuals are given (``clusters``, from :func:`carry_hull_track`). ``kwargs`` go to
    :func:`nsd.inference.single.decompose`.
    """
    common = dict(
        colour_sigma=settings.colour_sigma,
        colour_models=settings.colour_models,
        speckle=settings.speckle,
        neighbours=settings.neighbours,
        evidence_threshold=evidence_threshold,
        evidence_softness=evidence_softness,
        **kwargs,
    )
    if not settings.multiview:
        return decompose(model, images, backgrounds, **common)
    if grid is None:
        raise ValueError("multi-view inference needs the hull's voxel grid (settings.grid)")
    if images.shape[0] % num_views:
        raise ValueError(f"{images.shape[0]} images are not whole instants of {num_views} views")
    was = model.training
    model.eval()
    try:
        dev = model_device(model)
        det = move(model.detector(images.to(dev), backgrounds.to(dev)), images.device)
    finally:
        model.train(was)
    ev = foreground_evidence(images, backgrounds, evidence_threshold, evidence_softness)
    k = model.cfg.num_windows
    split = _hull_split(model)
    # the contested pixels are found only where they change the bonus; there only the
    # windows of the individuals near the pixel may own it
    contest = CONTEST_BAND if settings.hull_contested != settings.hull_ownership else 0.0
    fused, slots, owners, bonus, allowed = [], [], [], [], []
    track = ClusterTrack(rules=settings.mixture) if track is None else track
    for i, s in enumerate(range(0, images.shape[0], num_views)):
        sl = slice(s, s + num_views)
        hull = multiview_proposals(ev[sl], grid, k, split=split, contest=contest, track=track,
                                   clustered=None if clusters is None else clusters[i])
        one = Detections(det.boxes[sl], det.depths[sl], det.presence[sl])
        f, slot = fuse_detections(
            one, hull.boxes, hull.depths, hull.valid, settings.window_blend, settings.depth
        )
        fused.append(f)
        slots.append(slot)
        owners.append(window_owners(hull.owners, slot))
        contested = hull.contested
        bonus.append(torch.where(contested, settings.hull_contested, settings.hull_ownership))
        if contest > 0:
            allowed.append(window_candidates(hull.candidates, slot, contested))
    cat = Detections(
        *(torch.cat([getattr(f, a) for f in fused]) for a in ("boxes", "depths", "presence"))
    )
    # one colour model per hull individual and instant, shared by its windows in every view
    groups = torch.cat([torch.where(slot >= 0, i * k + slot, -1) for i, slot in enumerate(slots)])
    dec = decompose(model, images, backgrounds, detections=cat, owner_prior=torch.cat(owners),
                    owner_bonus=torch.cat(bonus),
                    owner_allowed=torch.cat(allowed) if allowed else None, groups=groups,
                    **common)
    dec.slots = torch.cat(slots)
    return dec
