r"""Multi-subject bidirectional novel-view synthesis (NSD eq. 2-7), the model.

For a pair of views :math:`(v, w)` of the same instant:

1. the detector B gives each view N windows, depths and presences;
2. focal spatial transformers crop the windows; the encoder E gives each an
   appearance vector and a 3D latent cloud;
3. to re-synthesise view :math:`v` *from* view :math:`w` (eq. 2), each source
   window's cloud is rotated by :math:`R_{w \to v}` and decoded with the source
   appearance into a window image and mask;
4. the decoded windows are re-ordered into :math:`v`'s slots by the appearance
   association (eq. 4-5);
5. with the mask refiner (ours, :mod:`nsd.model.mask_refiner`) each decoded mask is
   sharpened by :math:`v`'s own window crops;
6. they are pasted back with :math:`v`'s own boxes (inverse focal ST) and
   composited by depth over :math:`v`'s median background (eq. 7);

and symmetrically for :math:`w` from :math:`v`: each reconstruction takes its
boxes, depths and background from the target view and its pose and
appearance from the other view. ``mode="autoencoder"`` re-synthesises each view
from itself (the paper's auto-encoder ablation, our default: docs/nsd.md); ``depth=False`` uses the
additive compositor of eq. 6 (the no-depth ablation); ``focal=False`` the
classical spatial transformer.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

import torch
from torch import Tensor, nn

from nsd.cameras.batch import CameraBatch
from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.cues.triangulation import ray_distances, window_rays
from nsd.model.association import (
    appearance_similarity,
    apply_association,
    association_softmax,
    exclude_absent,
    hard_association,
)
from nsd.model.compositor import (
    Composite,
    additive_composite,
    blend,
    erf_transmittance_composite,
    masks_overlap,
    separate_composite,
)
from nsd.model.decoder import Decoder
from nsd.model.detector import Detections, Detector
from nsd.model.encoder import Encoder, rotate_latent
from nsd.model.focal_st import crop, paste
from nsd.model.mask_refiner import MaskRefiner
from nsd.model.window_masks import MASK_NORMALISATIONS, normalise_window_masks

__all__ = ["BiNVS", "BiNVSConfig", "Rendering", "Windows", "check_num_windows"]


def check_num_windows(k: int | str) -> None:
    """``model.num_windows`` is ``auto`` (settled for a scene: nsd.training.window_count) or an
    integer >= 1; else a ConfigError naming the key."""
    if k != "auto" and (isinstance(k, bool) or not isinstance(k, int) or k < 1):
        raise ConfigError(f"model.num_windows must be auto or an integer >= 1, got {k!r}")


@dataclass
class BiNVSConfig(ConfigSection):
    """How windows are cropped, associated and composited (every field a config value)."""

    APP: ClassVar[str] = "train"  # defaults: conf/train.yaml, section `model`
    KEY: ClassVar[str] = "model"
    SIBLINGS: ClassVar[frozenset[str]] = frozenset(
        {"detector", "encoder", "decoder", "mask_refiner", "depth_from_step", "reinit_at_depth"}
    )  # keys of the section read by other objects

    num_windows: int | str  # N: subjects per frame (an upper bound when presence is on); auto
    crop_size: int  # h = w of the window crops
    focal: bool  # focal spatial transformer (False: classical, for the ablation)
    depth: bool  # erf-transmittance compositor (False: additive eq. 6, ablation)
    mode: str  # "autoencoder" (each view from itself, the default) or "bi_nvs" (from the other)
    association: bool  # appearance association across views (eq. 4-5)
    association_dims: int  # leading appearance entries compared
    association_beta: float  # softmax sharpness
    association_geometry: float  # weight of the ray-distance term (0: appearance only, NSD)
    association_unit: float  # metres of ray distance per unit of cosine similarity
    # "max": divide each window's mask by its maximum (reference code); "visible": by the
    # maximum of its pooled, bump-weighted (pasted) mask (nsd/model/window_masks.py); "none"
    mask_normalisation: str
    mask_floor: float  # floor of that maximum
    mask_pool: int  # averaging window of "visible" (odd)
    crop_padding: str  # grid_sample padding of crops reaching outside the frame
    # how presence acts on the pasted masks in training: "soft" scales them by it, "hard" keeps
    # only windows with presence >= 0.5 (a detached 0/1 gate), "none" leaves them ungated
    presence_gate: str

    def validate(self) -> None:
        check_num_windows(self.num_windows)
        if self.mode not in ("bi_nvs", "autoencoder"):
            raise ConfigError(f"model.mode must be 'bi_nvs' or 'autoencoder', got {self.mode!r}")
        if self.mask_normalisation not in MASK_NORMALISATIONS:
            raise ConfigError(
                f"model.mask_normalisation must be one of {MASK_NORMALISATIONS}, "
                f"got {self.mask_normalisation!r}"
            )
        if self.mask_pool < 1 or self.mask_pool % 2 == 0:
            raise ConfigError(f"model.mask_pool must be an odd number >= 1, got {self.mask_pool}")
        if self.presence_gate not in ("soft", "hard", "none"):
            raise ConfigError(
                f"model.presence_gate must be 'soft', 'hard' or 'none', got {self.presence_gate!r}"
            )
        if not 1 <= self.association_dims:
            raise ConfigError("model.association_dims must be >= 1")


@dataclass
class Windows:
    """The windows of a batch of frames of one view.

    Attributes:
        det: boxes (B, N, 4), depths (B, N), presence (B, N).
        crops: (B, N, 3, h, w) (vignetted by the bump when focal).
        app: appearance vectors (B, N, D).
        latent: 3D latent clouds (B, N, P, 3) in this view's camera frame.
        on: (B, N) bool, windows that were encoded (None: all of them).
    """

    det: Detections
    crops: Tensor
    app: Tensor
    latent: Tensor
    on: Tensor | None = None

    def _map(self, fn) -> Windows:
        det = Detections(fn(self.det.boxes), fn(self.det.depths), fn(self.det.presence))
        on = None if self.on is None else fn(self.on)
        return Windows(det, fn(self.crops), fn(self.app), fn(self.latent), on)

    def halves(self, B: int) -> tuple[Windows, Windows]:
        """The first ``B`` frames' windows and the rest's."""
        return self._map(lambda t: t[:B]), self._map(lambda t: t[B:])

    def swapped(self, B: int) -> Windows:
        """The frames from ``B`` on first, then the first ``B``: each view of a pair of
        views stacked (v then w) faces the other's windows."""
        return self._map(lambda t: torch.cat([t[B:], t[:B]]))


@dataclass
class Rendering:
    """A re-synthesised full frame.

    Attributes:
        image: (B, 3, H, W).
        composite: weights (instance masks), background weight and depth map.
        layers: pasted subject images (B, N, 3, H, W).
        masks: pasted subject masks (B, N, H, W) (after association and presence).
        ungated_masks: the same before presence and switch-off (B, N, H, W).
        association: (B, N, N) soft (training) or one-hot (inference) association.
        window_rgb, window_mask: the decoded windows in target slots, (B, N, 3|1, h, w) (the
            mask refined when the model has a refiner).
        occlusion_reasoning: False when the masks did not overlap and the erf compositor's
            pairwise terms were skipped (its exact non-overlapping form was used).
    """

    image: Tensor
    composite: Composite
    layers: Tensor
    masks: Tensor
    association: Tensor
    window_rgb: Tensor
    window_mask: Tensor
    occlusion_reasoning: bool = True
    ungated_masks: Tensor | None = None

    def halves(self, B: int) -> tuple[Rendering, Rendering]:
        """The first ``B`` frames' rendering and the rest's (one render of both views of
        pairs, split back into one per view)."""
        first, rest = {}, {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Composite):
                first[f.name], rest[f.name] = (Composite(*(t[s] for t in value))
                                               for s in (slice(0, B), slice(B, None)))
            elif isinstance(value, Tensor):
                first[f.name], rest[f.name] = value[:B], value[B:]
            else:  # a flag both halves share
                first[f.name] = rest[f.name] = value
        return Rendering(**first), Rendering(**rest)


class BiNVS(nn.Module):
    """Detector B, encoder E, decoder D and the optional mask refiner, with the Bi-NVS
    forward pass."""

    def __init__(
        self, cfg: BiNVSConfig, detector: Detector, encoder: Encoder, decoder: Decoder,
        refiner: MaskRefiner | None = None,
    ) -> None:
        super().__init__()
        cfg.validate()
        if detector.num_windows != cfg.num_windows:
            raise ConfigError(
                f"detector has {detector.num_windows} windows but model.num_windows is "
                f"{cfg.num_windows}"
            )
        self.cfg, self.detector, self.encoder, self.decoder = cfg, detector, encoder, decoder
        self.refiner = refiner

    def windows(
        self,
        images: Tensor,
        backgrounds: Tensor,
        min_presence: float | None = None,
        detections: Detections | None = None,
    ) -> Windows:
        """Detect, crop and encode the windows of frames (B, 3, H, W).

        Args:
            images, backgrounds: (B, 3, H, W).
            min_presence: windows whose presence is below this are switched off: they are
                neither cropped nor encoded (their crops, appearance and latent are zeros).
                None: every window is encoded (training).
            detections: windows to use instead of the detector's (e.g. fused with the
                visual hull, :mod:`nsd.inference.multiview`); None: run the detector.
        """
        det = self.detector(images, backgrounds) if detections is None else detections
        size = (self.cfg.crop_size, self.cfg.crop_size)
        B, N = det.presence.shape
        if min_presence is None:
            crops = crop(
                images, det.boxes, size, focal=self.cfg.focal, padding_mode=self.cfg.crop_padding
            )
            app, latent = self.encoder(crops.flatten(0, 1))
            return Windows(det, crops, app.view(B, N, -1), latent.view(B, N, *latent.shape[1:]))
        on = det.presence >= min_presence  # (B, N)
        crops = images.new_zeros(B, N, images.shape[1], *size)
        app = images.new_zeros(B, N, self.encoder.app_dims)
        latent = images.new_zeros(B, N, self.encoder.points, 3)
        if on.any():
            b_idx, n_idx = torch.nonzero(on, as_tuple=True)
            c = crop(
                images[b_idx],
                det.boxes[b_idx, n_idx][:, None],
                size,
                focal=self.cfg.focal,
                padding_mode=self.cfg.crop_padding,
            )[:, 0]
            a, lat = self.encoder(c)
            crops[b_idx, n_idx], app[b_idx, n_idx], latent[b_idx, n_idx] = c, a, lat
        return Windows(det, crops, app, latent, on)

    def present(self, windows: Windows) -> Tensor | None:
        """(B, N) bool: the windows that may supply content (None: all of them).

        At inference the windows that were encoded; in training under the hard presence
        gate the windows with presence >= 0.5 (an off window's mask is gated out in its
        own view, so its decoding must not fill another view's slot either).
        """
        if windows.on is not None:
            return windows.on
        if self.cfg.presence_gate == "hard":
            return windows.det.presence.detach() >= 0.5
        return None

    def association_score(
        self, app_target: Tensor, app_source: Tensor, geometry_cost: Tensor | None = None
    ) -> Tensor:
        """Association score (B, N, M): cosine similarity minus the weighted ray distance."""
        M = appearance_similarity(app_target, app_source, self.cfg.association_dims)
        if geometry_cost is not None and self.cfg.association_geometry > 0:
            M = M - self.cfg.association_geometry * geometry_cost / self.cfg.association_unit
        return M

    def render(
        self,
        target: Windows,
        source: Windows,
        rotation: Tensor,
        background: Tensor,
        hard: bool = False,
        associate: bool | None = None,
        geometry_cost: Tensor | None = None,
    ) -> Rendering:
        """Re-synthesise the target view from the source view's windows.

        Args:
            target: windows of the view to synthesise (boxes, depths, presence used).
            source: windows providing pose (latent) and appearance.
            rotation: :math:`R_{source \\to target}`, (B, 3, 3).
            background: the target view's median background, (B, 3, H, W).
            hard: one-hot association (inference) instead of the softmax.
            associate: override ``cfg.association`` (False when source is target).
            geometry_cost: ray distances between target and source windows (B, N, N),
                metres; subtracted from the similarity with ``association_geometry``.
        """
        rgb, mask = self._decode(source, rotation)
        associate = self.cfg.association if associate is None else associate
        B, N = source.app.shape[:2]
        if associate:
            M = exclude_absent(
                self.association_score(target.app, source.app, geometry_cost),
                self.present(source),
            )
            A = hard_association(M) if hard else association_softmax(M, self.cfg.association_beta)
            rgb, mask = apply_association(A, rgb), apply_association(A, mask)
        else:
            A = torch.eye(N, dtype=rgb.dtype, device=rgb.device).expand(B, N, N)
        if self.refiner is not None:
            mask = self._refine(target, background, rgb, mask)
        H, W = background.shape[-2:]
        boxes = target.det.boxes
        layers = paste(rgb, boxes, (H, W), focal=self.cfg.focal, padding_mode="border")
        masks = paste(mask, boxes, (H, W), focal=self.cfg.focal, padding_mode="zeros")[:, :, 0]
        ungated = masks = masks.clamp(0.0, 1.0)
        masks = self._gate(masks, target)
        comp, occlusion = self._composite(masks, target)
        return Rendering(
            blend(comp, layers, background),
            comp,
            layers,
            masks,
            A,
            rgb,
            mask,
            occlusion_reasoning=occlusion,
            ungated_masks=ungated,
        )

    def _decode(self, source: Windows, rotation: Tensor) -> tuple[Tensor, Tensor]:
        """Crop colours (B, N, 3, c, c) and normalised masks (B, N, 1, c, c) of the source's
        windows, their latent rotated into the target view; switched-off windows are empty."""
        B, N = source.app.shape[:2]
        latent = rotate_latent(source.latent, rotation.to(source.latent.dtype))
        if source.on is None:
            rgb, logit = self.decoder(latent.flatten(0, 1), source.app.flatten(0, 1))
            rgb = rgb.view(B, N, *rgb.shape[1:])
            mask = torch.sigmoid(logit).view(B, N, *logit.shape[1:])
        else:  # switched-off windows are not decoded: empty windows
            c = self.cfg.crop_size
            rgb = latent.new_zeros(B, N, 3, c, c)
            mask = latent.new_zeros(B, N, 1, c, c)
            if source.on.any():
                b_idx, n_idx = torch.nonzero(source.on, as_tuple=True)
                r_, l_ = self.decoder(latent[b_idx, n_idx], source.app[b_idx, n_idx])
                rgb[b_idx, n_idx], mask[b_idx, n_idx] = r_, torch.sigmoid(l_)
        mask = normalise_window_masks(
            mask, self.cfg.mask_normalisation, self.cfg.focal, self.cfg.mask_floor,
            self.cfg.mask_pool,
        )
        return rgb, mask

    def _refine(self, target: Windows, background: Tensor, rgb: Tensor, mask: Tensor) -> Tensor:
        """The decoded masks in the target's slots (B, N, 1, c, c) sharpened by the target
        windows' image and background crops (:mod:`nsd.model.mask_refiner`), normalised again."""
        size = (self.cfg.crop_size, self.cfg.crop_size)
        bg = crop(background, target.det.boxes, size, focal=self.cfg.focal,
                  padding_mode=self.cfg.crop_padding)
        logit = self.refiner(target.crops, bg, rgb, mask)
        return normalise_window_masks(
            torch.sigmoid(logit), self.cfg.mask_normalisation, self.cfg.focal,
            self.cfg.mask_floor, self.cfg.mask_pool,
        )

    def _gate(self, masks: Tensor, target: Windows) -> Tensor:
        """Pasted masks (B, N, H, W) gated by presence (``presence_gate``) and, at inference,
        by which windows are on."""
        if self.cfg.presence_gate == "soft":
            masks = masks * target.det.presence[..., None, None]
        elif self.cfg.presence_gate == "hard":  # no image gradient into the presence
            masks = masks * (target.det.presence.detach() >= 0.5)[..., None, None].to(masks.dtype)
        if target.on is not None:  # inference: skip occlusion reasoning without overlaps
            masks = masks * target.on[..., None, None]
        return masks

    def _composite(self, masks: Tensor, target: Windows) -> tuple[Composite, bool]:
        """The compositor's weights, and whether occlusion reasoning was needed."""
        if not self.cfg.depth:
            return additive_composite(masks, target.det.depths), True
        if target.on is not None and not masks_overlap(masks).any():
            return separate_composite(masks, target.det.depths), False
        return erf_transmittance_composite(masks, target.det.depths), True

    def forward(
        self,
        image_v: Tensor,
        image_w: Tensor,
        background_v: Tensor,
        background_w: Tensor,
        rotation_vw: Tensor,
        cameras_v: CameraBatch | None = None,
        cameras_w: CameraBatch | None = None,
    ) -> tuple[Rendering, Rendering, Windows, Windows]:
        """Both directions of Bi-NVS for a batch of view pairs.

        Args:
            image_v, image_w: (B, 3, H, W) the two views of the same instants.
            background_v, background_w: their median backgrounds.
            rotation_vw: :math:`R_{v \\to w}`, (B, 3, 3).
            cameras_v, cameras_w: per-sample K, R, t, dist of the two views; needed for
                the geometric association term (``association_geometry > 0``).

        Returns:
            (rendering of v, rendering of w, windows of v, windows of w).
        """
        both = self.windows(torch.cat([image_v, image_w]), torch.cat([background_v, background_w]))
        B = image_v.shape[0]
        win_v, win_w = both.halves(B)
        backgrounds = torch.cat([background_v, background_w])
        # both directions in one render: targets v then w, sources w then v
        if self.cfg.mode == "autoencoder":
            eye = torch.eye(3, dtype=image_v.dtype, device=image_v.device).expand(2 * B, 3, 3)
            rendered = self.render(both, both, eye, backgrounds, associate=False)
        else:
            cost = None
            if self.cfg.association_geometry > 0 and cameras_v is not None:
                cost = self.geometry_cost(
                    win_v.det.boxes, win_w.det.boxes, cameras_v, cameras_w, image_v.shape[-2:]
                )
                cost = torch.cat([cost, cost.transpose(-1, -2)])
            rotations = torch.cat([rotation_vw.transpose(-1, -2), rotation_vw])
            rendered = self.render(both, both.swapped(B), rotations, backgrounds,
                                   geometry_cost=cost)
        render_v, render_w = rendered.halves(B)
        return render_v, render_w, win_v, win_w

    @staticmethod
    def geometry_cost(
        boxes_v: Tensor,
        boxes_w: Tensor,
        cameras_v: CameraBatch,
        cameras_w: CameraBatch,
        image_size,
    ) -> Tensor:
        """Ray distances (B, N_v, N_w) between the window centres of two views (detached).

        Args:
            boxes_v, boxes_w: windows (B, N, 4) of the two views.
            cameras_v, cameras_w: per-sample K (B, 3, 3), R, t, dist.
            image_size: (H, W) of the frames.
        """
        with torch.no_grad():
            o_v, d_v = window_rays(
                boxes_v,
                cameras_v.K,
                cameras_v.R,
                cameras_v.t,
                cameras_v.dist,
                tuple(image_size),
            )
            o_w, d_w = window_rays(
                boxes_w,
                cameras_w.K,
                cameras_w.R,
                cameras_w.t,
                cameras_w.dist,
                tuple(image_size),
            )
            return ray_distances(o_v, d_v, o_w, d_w)
