r"""NNOPCS: normalised neutral object pose and coordinate space (NeTePu, Sec. 3.1).

The NNOPCS value of a surface point is its 3D coordinate in the species' neutral
(rest) pose, normalised to :math:`[0, 1]^3`, so that the same body point has the
same value in every pose and every view.

Definition used by the synthetic world
    A surface point lies on one ellipsoid ``p`` of an individual. In ``p``'s
    local frame, scaled by its semi-axes, it is a point ``u`` on the unit
    sphere (:mod:`nsd.synth.raycast` returns ``u`` for every hit). Its *canonical*
    point is that ``u`` placed on the same ellipsoid of the species' **mean
    body** in the rest pose,

    .. math::
        \bar P = \bar c_p + \bar Q_p (\bar a_p \odot u),

    and its NNOPCS value is :math:`(\bar P - m) / s + 1/2`, clamped to
    :math:`[0, 1]`, with ``m`` the centre of the mean body's rest-pose bounding
    box and ``s`` its longest side times :math:`1 + 2\cdot` :data:`NNOPCS_MARGIN`
    (one isotropic scale, so shapes are not stretched; the body is centred in
    the cube).

    Going through the mean body makes the value independent of pose, camera
    *and* the individual's proportions: the same anatomical point (the tip of
    the left ear) has the same NNOPCS value on every individual of a species,
    so textures defined on NNOPCS (:mod:`nsd.synth.texture`) stick to the body
    and carry identity only. Canonical points lie on the mean body's ellipsoids,
    hence inside the bounds; the clamp only guards rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import torch
from torch import Tensor

from nsd.synth.skeleton import Species

__all__ = [
    "NNOPCS_MARGIN",
    "NNOPCSBounds",
    "canonical_points",
    "ellipsoid_half_extents",
    "nnopcs_bounds",
    "nnopcs_of",
    "species_primitives",
]

NNOPCS_MARGIN = 0.02  # fraction of the longest side added on every side of the box


def ellipsoid_half_extents(axes: Tensor, radii: Tensor) -> Tensor:
    """Half-size of the axis-aligned box around ellipsoids.

    Args:
        axes: local axes as columns, shape (..., 3, 3).
        radii: semi-axes, shape (..., 3).

    Returns:
        Half extents along world x, y, z, shape (..., 3).
    """
    return torch.sqrt(((axes * radii.unsqueeze(-2)) ** 2).sum(-1))


@cache
def species_primitives(species: Species) -> tuple[Tensor, Tensor, Tensor]:
    """Mean-body rest primitives: centres (P, 3), axes (P, 3, 3), radii (P, 3), float64."""
    c = torch.tensor([p.centre for p in species.primitives], dtype=torch.float64)
    q = torch.tensor([p.axes for p in species.primitives], dtype=torch.float64)
    a = torch.tensor([p.radii for p in species.primitives], dtype=torch.float64)
    return c, q, a


@dataclass(frozen=True)
class NNOPCSBounds:
    """The normalisation of one species: ``nnopcs = (P - centre) / extent + 0.5``.

    Attributes:
        centre: centre of the mean body's rest bounding box, (3,) metres.
        extent: side of the NNOPCS cube, metres.
        lo, hi: the mean body's rest bounding box, (3,) metres.
    """

    centre: tuple[float, float, float]
    extent: float
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        # a flat body (zero size along some axes) is fine: the cube's side is the
        # longest side; only a body of zero size along every axis cannot be normalised
        if not math.isfinite(self.extent) or self.extent <= 0:
            raise ValueError(
                f"NNOPCS extent must be a positive finite length, got {self.extent} "
                f"(bounding box {self.lo} .. {self.hi}): the species' mean body has zero "
                "size along every axis; give its primitives non-zero radii"
            )

    def normalise(self, points: Tensor) -> Tensor:
        """Rest-pose points (..., 3) metres -> NNOPCS (..., 3), clamped to [0, 1]."""
        centre = torch.as_tensor(self.centre, dtype=points.dtype, device=points.device)
        return ((points - centre) / self.extent + 0.5).clamp(0.0, 1.0)

    def denormalise(self, nnopcs: Tensor) -> Tensor:
        """NNOPCS (..., 3) -> mean-body rest-pose points (..., 3) metres."""
        centre = torch.as_tensor(self.centre, dtype=nnopcs.dtype, device=nnopcs.device)
        return (nnopcs - 0.5) * self.extent + centre

    def to_json(self) -> dict:
        return {
            "centre": list(self.centre),
            "extent": self.extent,
            "lo": list(self.lo),
            "hi": list(self.hi),
        }


@cache
def nnopcs_bounds(species: Species) -> NNOPCSBounds:
    """The fixed NNOPCS normalisation of ``species`` (see the module docstring)."""
    c, q, a = species_primitives(species)
    half = ellipsoid_half_extents(q, a)
    lo = (c - half).min(0).values
    hi = (c + half).max(0).values
    extent = float((hi - lo).max()) * (1.0 + 2.0 * NNOPCS_MARGIN)
    return NNOPCSBounds(
        centre=tuple(((lo + hi) / 2).tolist()),
        extent=extent,
        lo=tuple(lo.tolist()),
        hi=tuple(hi.tolist()),
    )


def canonical_points(species: Species, part: Tensor, local: Tensor) -> Tensor:
    """Mean-body rest-pose points of surface points given per primitive.

    Args:
        species: the species.
        part: primitive index per point, int64 shape (N,).
        local: points in the primitive's unit-sphere coordinates, shape (N, 3).

    Returns:
        :math:`\\bar c_p + \\bar Q_p (\\bar a_p \\odot u)`, shape (N, 3), dtype of ``local``.
    """
    c, q, a = (x.to(local.dtype) for x in species_primitives(species))
    return c[part] + ((q[part] * a[part].unsqueeze(-2)) @ local.unsqueeze(-1)).squeeze(-1)


def nnopcs_of(species: Species, part: Tensor, local: Tensor) -> Tensor:
    """NNOPCS values (N, 3) in [0, 1] of surface points (see :func:`canonical_points`)."""
    return nnopcs_bounds(species).normalise(canonical_points(species, part, local))
