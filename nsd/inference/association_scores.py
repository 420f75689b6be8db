"""The trained model's association score between the windows of two views of one instant.

Appearance similarity plus the geometric term of the calibrated cameras
(:meth:`nsd.model.bi_nvs.BiNVS.association_score`), and with multi-view inference a bonus
where both windows were fused with the same visual-hull individual.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from nsd.cameras.batch import CameraBatch
from nsd.core.device import call_on_device

__all__ = ["association_scores"]


def association_scores(
    model,
    dec,
    cameras: CameraBatch,
    image_size: Sequence[int],
    v: int,
    w: int,
    slot_bonus: float = 0.0,
) -> torch.Tensor:
    """The model's association score (N, N) between the windows of views v and w of a frame.

    Args:
        model: the trained BiNVS.
        dec: the frame's :class:`nsd.inference.single.Decomposition` (one entry per view).
        cameras: stacked per-view K (V, 3, 3), R, t, dist at ``image_size``
            (:meth:`nsd.cameras.calibration.CameraRig.stacked`).
        image_size: (H, W) of the decomposed frames.
        v, w: the two views.
        slot_bonus: added where both windows were fused with the same visual-hull
            individual (``dec.slots``, multi-view inference, :mod:`nsd.inference.multiview`).
    """
    def scores(win_v, win_w, cam_v, cam_w, app_v, app_w):
        cost = model.geometry_cost(win_v, win_w, cam_v, cam_w, tuple(image_size))
        return model.association_score(app_v, app_w, cost)[0]

    score = call_on_device(
        model, scores, dec.windows[v][None], dec.windows[w][None], cameras[v], cameras[w],
        dec.app[v][None], dec.app[w][None],
    )
    slots = getattr(dec, "slots", None)
    if slots is not None and slot_bonus > 0:
        a, b = slots[v], slots[w]
        same = (a[:, None] == b[None, :]) & (a[:, None] >= 0)
        score = score + slot_bonus * same.to(score.dtype)
    return score
