r"""The texture code's re-identification embedding: colour statistics and within-class whitening.

Colour statistics (:func:`colour_statistics`)
    Re-identification reads the texture code together with six numbers of the
    encoder's masked crop: the log of the mean colour inside the mask and the
    colour's standard deviation inside the mask, per channel,

    .. math::
        c = \big(\log(\bar a + \epsilon),\ \sigma_a\big), \qquad
        \bar a = \tfrac{1}{|M|}\sum_{p \in M} a_p, \quad
        \sigma_a^2 = \tfrac{1}{|M|}\sum_{p \in M} (a_p - \bar a)^2,

    (:math:`\epsilon = 1/255`). Under Lambertian shading a colour is the albedo
    times a grey shading term, so a change of light or view moves
    :math:`\log \bar a` along :math:`(1, 1, 1)` (for shading uncorrelated with
    albedo); that is within-class variation, which the whitening below learns to
    discount, while a small difference of albedo (the look-alike pairs) is not.
    The code alone keeps the mean colour only coarsely (NeTePu's renderer needs
    it only to within its PSNR).

Within-class whitening (:func:`within_class_whitening`)
    A linear map fitted on labelled training codes that equalises the
    directions in which one identity's codes vary (pose, camera, shading):
    with the within-class scatter
    :math:`S_w = \frac1N \sum_i (x_i - m_{y_i})(x_i - m_{y_i})^\top`
    (:math:`m_c` the mean of identity c), its eigen-decomposition
    :math:`S_w = V \Lambda V^\top` and shrinkage
    :math:`\lambda' = \lambda \operatorname{tr}(S_w) / D`,

    .. math::
        e = (x - m) P, \qquad P = V (\Lambda + \lambda' I)^{-1/2},

    with m the mean of all training codes, so that
    :math:`P^\top (S_w + \lambda' I) P = I` (WCCN, as in speaker
    verification). Directions that identities share are scaled up, the
    within-identity spread down; no dimension is dropped, so it also serves
    identities never seen in the fit (unlike LDA, which keeps C - 1 directions).

Shrinkage by validation (:func:`select_shrinkage`)
    The whitening's shrinkage is chosen on the training codes alone: two folds
    of training views, each fitted on one fold and scored (cross-camera rank-1,
    then mAP) on the other; the mean over both folds picks the grid value (the
    largest on ties).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from nsd.evaluation.reid import reid_metrics

__all__ = [
    "COLOUR_EPS",
    "COLOUR_STATISTICS",
    "colour_statistics",
    "select_shrinkage",
    "within_class_whitening",
]


COLOUR_STATISTICS = 6  # log mean colour (3) and colour standard deviation (3)


COLOUR_EPS = 1.0 / 255


def colour_statistics(rgb: Tensor, inside: Tensor) -> Tensor:
    """Masked colour statistics of crops (module docstring).

    Args:
        rgb: (B, S, S, 3) colours in [0, 1]; inside: (B, S, S) bool, the pixels that count.

    Returns:
        (B, 6): log(mean colour + 1/255) and the colour's standard deviation, per
        channel, over the pixels inside; log(1/255) and 0 for an empty mask.
    """
    w = inside.to(rgb.dtype)[..., None]
    n = w.sum((1, 2)).clamp(min=1)
    mean = (rgb * w).sum((1, 2)) / n
    var = ((rgb - mean[:, None, None]) ** 2 * w).sum((1, 2)) / n
    return torch.cat([torch.log(mean + COLOUR_EPS), var.sqrt()], -1)


def select_shrinkage(
    codes: np.ndarray,
    labels: np.ndarray,
    cameras: np.ndarray,
    groups: np.ndarray,
    grid: tuple[float, ...] = (0.1, 0.01, 0.001, 0.0001),
) -> tuple[float, dict[float, float]]:
    """The whitening shrinkage that re-identifies best across two folds of training codes.

    Args:
        codes: (N, D); labels: (N,) identities; cameras: (N,) camera ids.
        groups: (N,) ordered group ids (e.g. training views, so that one view never sits in
            both folds); fold 1 holds the groups >= their median, fold 0 the others.
        grid: shrinkage values to try.

    Returns:
        ``(best, scores)``: ``scores[s]`` is the mean over both folds of the other fold's
        cross-camera rank-1 plus 1e-3 x its mAP; ties go to the larger shrinkage.

    Raises:
        ValueError: an empty grid, a fold with fewer than two identities, or a fold
            without a query that has a match in another camera.
    """
    if not grid:
        raise ValueError("select_shrinkage: the grid is empty")
    codes, labels = np.asarray(codes, np.float64), np.asarray(labels)
    cameras, groups = np.asarray(cameras), np.asarray(groups)
    folds = (groups >= np.median(groups)).astype(np.int64)
    scores = {}
    for shrinkage in sorted(grid, reverse=True):
        total = 0.0
        for fit in (0, 1):
            a, b = folds == fit, folds != fit
            if len(np.unique(labels[a])) < 2:
                raise ValueError(f"select_shrinkage: fold {fit} holds fewer than 2 identities")
            m, p = within_class_whitening(codes[a], labels[a], shrinkage)
            r = reid_metrics((codes[b] - m) @ p, labels[b], cameras[b])
            if not r["queries"]:
                raise ValueError(
                    f"select_shrinkage: no code of fold {1 - fit} has a match in another camera"
                )
            total += r["rank1"] + 1e-3 * r["map"]
        scores[float(shrinkage)] = total / 2
    best = max(scores, key=lambda k: (scores[k], k))
    return best, scores


def within_class_whitening(
    codes: np.ndarray, labels: np.ndarray, shrinkage: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Fit the within-class whitening (module docstring) on labelled codes.

    Args:
        codes: (N, D) training codes; labels: (N,) their identities (>= 2 distinct).
        shrinkage: lambda >= 0, relative to the mean eigenvalue of S_w.

    Returns:
        ``(m (D,), P (D, D))`` float64: the embedding of x is ``(x - m) @ P``.

    Raises:
        ValueError: fewer than two identities, a negative shrinkage, non-finite codes,
            or a singular scatter with no shrinkage.
    """
    x = np.asarray(codes, np.float64)
    y = np.asarray(labels)
    if x.ndim != 2 or len(x) != len(y):
        raise ValueError(f"whitening: codes (N, D) and labels (N,), got {x.shape}, {y.shape}")
    if shrinkage < 0 or not np.isfinite(x).all():
        raise ValueError("whitening: shrinkage must be >= 0 and the codes finite")
    classes, index = np.unique(y, return_inverse=True)
    if len(classes) < 2:
        raise ValueError(f"whitening: needs >= 2 identities, got {len(classes)}")
    means = np.stack([x[index == c].mean(0) for c in range(len(classes))])
    # the product and eigen-decomposition in torch (float64): its pinned build, not NumPy's
    # BLAS of whatever version, decides the rounding, so a retrained model is the same file
    # (tools/train_species_models.py --check)
    centred = torch.from_numpy(x - means[index])
    scatter = centred.T @ centred / len(x)
    ev, vec = torch.linalg.eigh(scatter)
    ev = ev + shrinkage * max(float(torch.trace(scatter)), 0.0) / x.shape[1]
    if float(ev.min()) <= 1e-12 * max(float(ev.max()), 1e-300):
        raise ValueError(
            "whitening: the within-class scatter is singular (too few codes per dimension); "
            "give a shrinkage > 0"
        )
    return x.mean(0), (vec / ev.sqrt()).numpy()
