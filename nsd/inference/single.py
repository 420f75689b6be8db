r"""Inference API: frames in, one record per subject out (no autograd, batched).

At test time NSD needs a single image: the detector places the windows, the
encoder encodes them, the decoder renders each window in its own view (no
rotation) and the compositor resolves occlusions with the predicted depths.
The composited weights are the *raw* visible instance masks.

Mask refinement (``refine="residual"``, the default): the decoder renders
small windows (32 px by default) and misses thin limbs, so the visible masks
are re-drawn from the background residual: every foreground pixel (evidence
above 0.5, see :func:`nsd.cues.evidence.foreground_evidence`) goes to the subject
with the largest ownership score there (if its composited weight exceeds
``min_weight``). The ownership score of subject :math:`i` at pixel :math:`p`
(:func:`ownership`) is its composited weight times the agreement of its
decoded colour :math:`L_i(p)` with the image :math:`I(p)`,

.. math::
    o_i(p) = w_i(p)\, \exp\!\left(-\frac{\lVert I(p) - L_i(p) \rVert^2}{2 \sigma_c^2}\right),

so that where two blobby decoded masks overlap, the pixel goes to the subject
whose rendering looks like it (``colour_sigma`` :math:`\sigma_c`; 0 uses the
weights alone). Multi-view inference adds, in the log domain, ``owner_bonus`` for the
subject whose visual-hull individual owns the pixel (:mod:`nsd.inference.multiview`; a
smaller bonus where the hull cannot settle the owner), and the individuals' colour models,
learned from the pixels each owns surely, add the likelihood of the pixel's colour
(:mod:`nsd.inference.colour_models`). Neighbouring pixels of one colour are then drawn to
one owner, where colour tells their candidates apart (:mod:`nsd.inference.neighbours`).
NSD still decides which subject a pixel belongs to and who
occludes whom; the median background, which NSD already needs, only sharpens
the silhouettes. Their speckle is cleaned (:mod:`nsd.cues.holes`): the small holes a mask
encloses, where the body's colour is close to the floor's, are filled (``hole_share``), and a
subject's small islands inside another subject, where touching bodies share colours, are
given to it (``island_share``). ``refine="none"`` returns the raw masks.

Cross-view identities come from the appearance association: in each frame,
the windows of every view are matched one-to-one (Hungarian on the cosine
similarity of their association dims) to the windows of the reference view, the
view with the most active windows (the first of them on ties), so that every window
of a view that shows fewer subjects finds a partner; unmatched windows (only where
the reference's windows are too few) open new identities.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from nsd.core.device import model_device, move
from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence
from nsd.cues.holes import SPECKLE, Speckle
from nsd.inference.colour_models import ColourModels
from nsd.inference.neighbours import NEIGHBOURS_OFF, NeighbourAgreement
from nsd.model.association import appearance_similarity
from nsd.model.bi_nvs import BiNVS
from nsd.model.detector import Detections
from nsd.ops.boxes import mask_boxes_xywh

__all__ = ["COLOUR_SIGMA", "Decomposition", "associate_views", "decompose", "ownership"]

# The colour agreement of the ownership when no config gives one; conf/inference/default.yaml
# (``inference.colour_sigma``) holds the same value, chosen in docs/benchmarks/ownership.md.
COLOUR_SIGMA = 0.4


@dataclass
class Decomposition:
    """Per-subject results for a batch of B frames of one or more views.

    Attributes:
        windows: window boxes (B, N, 4) = (sx, sy, tx, ty), normalised.
        boxes: tight boxes of the visible masks, COCO pixels [x, y, w, h], (B, N, 4).
        masks: visible instance masks, (B, N, H, W) in [0, 1] (refined, see the module).
        raw_masks: the compositor's weights, (B, N, H, W).
        depths: (B, N), smaller is nearer.
        presence: (B, N) in [0, 1].
        scores: detection confidence (B, N) in [0, 1].
        active: (B, N) bool: present and with a non-empty visible mask.
        crops: (B, N, 3, h, w) the encoder's input crops.
        app: appearance vectors (B, N, D).
        latent: 3D latent clouds (B, N, P, 3).
        reconstruction: the frame re-synthesised from its own windows, (B, 3, H, W).
        occlusion_reasoning: False when no masks overlapped and the compositor's pairwise
            occlusion terms were skipped.
        slots: (B, N) long, the visual-hull individual each window was fused with
            (multi-view inference, :mod:`nsd.inference.multiview`; -1: none), else None.
    """

    windows: Tensor
    boxes: Tensor
    masks: Tensor
    raw_masks: Tensor
    depths: Tensor
    presence: Tensor
    scores: Tensor
    active: Tensor
    crops: Tensor
    app: Tensor
    latent: Tensor
    reconstruction: Tensor
    occlusion_reasoning: bool = True
    slots: Tensor | None = None


def ownership(weights: Tensor, layers: Tensor, images: Tensor, colour_sigma: float) -> Tensor:
    r"""Log ownership scores :math:`\log o_i(p)` (B, N, H, W) (module docstring).

    In the log domain, so that no colour disagreement, however large for a small
    ``colour_sigma``, underflows every subject's score to the same 0.

    Args:
        weights: composited visible weights (B, N, H, W).
        layers: each subject's decoded colour pasted into the frame, (B, N, 3, H, W).
        images: the frames (B, 3, H, W).
        colour_sigma: colour agreement scale (0: the weights alone).
    """
    log_w = weights.clamp_min(torch.finfo(weights.dtype).tiny).log()
    if colour_sigma <= 0:
        return log_w
    err = (images[:, None] - layers).pow(2).sum(2)
    return log_w - err / (2 * colour_sigma**2)


@torch.inference_mode()
def decompose(
    model: BiNVS,
    images: Tensor,
    backgrounds: Tensor,
    mask_threshold: float = 0.5,
    min_area: int = 4,
    presence_threshold: float = 0.5,
    refine: str = "residual",
    min_weight: float = 0.05,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
    colour_sigma: float = COLOUR_SIGMA,
    detections: Detections | None = None,
    owner_prior: Tensor | None = None,
    owner_bonus: float | Tensor = 0.0,
    owner_allowed: Tensor | None = None,
    colour_models: ColourModels | None = None,
    groups: Tensor | None = None,
    speckle: Speckle = SPECKLE,
    neighbours: NeighbourAgreement = NEIGHBOURS_OFF,
) -> Decomposition:
    """Decompose frames (B, 3, H, W) with their backgrounds into subjects.

    Args:
        model: a trained :class:`BiNVS` (put in eval mode here, restored after).
        images, backgrounds: (B, 3, H, W) in [0, 1].
        mask_threshold: visible-mask threshold for boxes, areas and ``active``.
        min_area: smallest visible area (pixels) of an active subject.
        presence_threshold: windows below this presence are inactive.
        refine: ``"residual"`` (silhouettes from the background residual) or ``"none"``.
        min_weight: smallest composited weight that claims a foreground pixel.
        evidence_threshold, evidence_softness: as in training (``loss`` config).
        colour_sigma: colour agreement of the refinement's ownership (:func:`ownership`).
        detections: windows to use instead of the detector's (:mod:`nsd.inference.multiview`).
        owner_prior: (B, H, W) the window another cue gives each pixel (-1: none), e.g. the
            visual hull's (:mod:`nsd.inference.multiview`); where ``owner_bonus`` (a number,
            or (B, H, W) per pixel) is > 0 its window's log ownership score gains
            ``owner_bonus`` and it may claim the pixel whatever its composited weight.
        owner_allowed: (B, N, H, W) bool, the windows that may own each pixel (e.g. on a
            pixel the hull cannot settle, those of the individuals near it); None: all.
        colour_models: the individuals' colour models added to the ownership
            (:mod:`nsd.inference.colour_models`); None: off.
        groups: (B, N) long, windows that share one colour model (the same id >= 0, e.g. one
            hull individual in every view of an instant); None: each window alone.
        speckle: with ``refine="residual"``, the masks' small holes filled and small
            islands given to the subject around them (:class:`nsd.cues.holes.Speckle`).
        neighbours: with ``refine="residual"``, the Potts term by which neighbouring pixels of
            one colour share an owner (:mod:`nsd.inference.neighbours`; its compatibility
            from ``colour_models``, Potts where they are off); default off.
    """
    was_training = model.training
    model.eval()
    dev = model_device(model)  # the model runs on its device, the rest on the CPU
    try:
        on_dev = move((images, backgrounds, detections), dev)
        win = model.windows(*on_dev[:2], presence_threshold, on_dev[2])
        B = images.shape[0]
        eye = torch.eye(3, dtype=images.dtype, device=dev).expand(B, 3, 3)
        r = model.render(win, win, eye, on_dev[1], hard=True, associate=False)
        win, r = move((win, r), images.device)
    finally:
        model.train(was_training)
    raw = r.composite.weights
    if refine == "residual":
        fg = foreground_evidence(images, backgrounds, evidence_threshold, evidence_softness) > 0.5
        weighted = raw * win.det.presence[..., None, None]
        score = ownership(weighted, r.layers, images, colour_sigma)
        claim = weighted.amax(1, keepdim=True) > min_weight
        if owner_prior is not None:
            bonus = torch.as_tensor(owner_bonus, dtype=score.dtype).expand(owner_prior.shape)
            slots = torch.arange(raw.shape[1])[None, :, None, None]
            prior = (owner_prior[:, None] == slots) & (bonus[:, None] > 0)  # (B, N, H, W)
            score = score + bonus[:, None] * prior
            claim = claim | prior.any(1, keepdim=True)
        if owner_allowed is not None:
            score = score - 1e4 * ~owner_allowed  # the learned order where none is allowed
        claim = fg[:, None] & claim
        compatibility = None
        if colour_models is not None:
            score, compatibility = colour_models.rescore_with_compatibility(
                score, images, claim[:, 0], groups)
        score = neighbours.rescore(score, images, claim[:, 0], compatibility)
        owner = score.max(1, keepdim=True).indices  # argmax (first on ties), 5x faster on CPU
        masks = (torch.arange(raw.shape[1])[None, :, None, None] == owner) & claim
        masks = speckle.clean_batch(masks.to(raw.dtype))
    elif refine == "none":
        masks = raw
    else:
        raise ValueError(f"refine must be 'residual' or 'none', got {refine!r}")
    binary = masks > mask_threshold
    area = binary.flatten(-2).sum(-1)
    active = win.on & (area >= min_area)
    conf = (raw * binary).flatten(-2).sum(-1) / area.clamp_min(1)
    return Decomposition(
        windows=win.det.boxes,
        boxes=mask_boxes_xywh(binary),
        masks=masks,
        raw_masks=raw,
        depths=win.det.depths,
        presence=win.det.presence,
        scores=win.det.presence * conf,
        active=active,
        crops=win.crops,
        app=win.app,
        latent=win.latent,
        reconstruction=r.image,
        occlusion_reasoning=r.occlusion_reasoning,
    )


def associate_views(
    app: Tensor,
    active: Tensor,
    dims: int = 16,
    score: Callable[[int, int], Tensor] | None = None,
) -> np.ndarray:
    """Cross-view subject ids for the windows of one frame.

    Args:
        app: appearance vectors of every view's windows, (V, N, D).
        active: (V, N) bool.
        dims: association dims (as in training).
        score: ``score(v, r)`` -> (N, N) association score between the windows of view
            ``v`` and the reference view ``r`` (e.g.
            :func:`nsd.inference.association_scores.association_scores`, which adds the
            geometric term); default: cosine similarity of ``app``.

    Returns:
        int array (V, N): the subject id of each window, -1 for inactive windows.
    """
    V, N = active.shape
    ids = np.full((V, N), -1, dtype=np.int64)
    on = active.cpu().numpy()
    ref = int(np.argmax(on.sum(1)))  # the view showing the most subjects, first on ties
    ref_act = np.flatnonzero(on[ref])
    if ref_act.size == 0:
        return ids
    ids[ref, ref_act] = np.arange(ref_act.size)
    next_id = ref_act.size
    for v in range(V):
        act = np.flatnonzero(on[v])
        if v == ref or act.size == 0:
            continue
        if score is None:
            full = appearance_similarity(app[v][None], app[ref][None], dims)[0]
        else:
            full = score(v, ref)
        sim = full[act][:, ref_act].cpu().numpy()
        rows, cols = linear_sum_assignment(-sim)
        ids[v, act[rows]] = ids[ref, ref_act[cols]]
        for i in np.setdiff1d(np.arange(act.size), rows):
            ids[v, act[i]] = next_id
            next_id += 1
    return ids
