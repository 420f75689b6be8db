r"""Procedural textures that define identity, as functions of NNOPCS coordinates.

A texture maps an NNOPCS value :math:`p \in [0, 1]^3` (:mod:`nsd.synth.nnopcs`)
to an albedo in :math:`[0, 1]^3`. Because NNOPCS is the point's coordinate in
the neutral pose of the species' mean body, the texture sticks to the body in
every pose and view, and the same texture id looks the same on individuals of
different proportions.

A texture is a base colour plus, optionally,

* a pattern in a secondary colour: ``solid`` (none), ``patches`` (a smooth
  random field thresholded to a coverage, like Holstein patches), ``spots``
  (discs of random size on a jittered grid: freckles or spots), ``stripes``
  (a warped sinusoid along an axis: brindle), ``band`` (one band across the
  body: belted), ``gradient`` (base to secondary along an axis);
* ``low``: a colour below an NNOPCS height (dark legs, stockings, boots);
* ``face``: a colour in front of an NNOPCS x (a white face on quadrupeds);
* ``grain``: fine multiplicative colour noise.

Pool and look-alikes
    Ids ``0 .. POOL_SIZE - 1`` are a fixed, hand-made pool. It deliberately holds
    pairs that are hard to tell apart (as NePuMoo's textures 1/11 and 9/10):
    :data:`LOOK_ALIKE_PAIRS`. Ids ``>= POOL_SIZE`` are generated from the id (a
    random pattern, colours and parameters), so re-identification can be tested
    on individuals whose textures were never seen in training.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from nsd.core.errors import ConfigError

__all__ = [
    "LOOK_ALIKE_PAIRS",
    "PATTERNS",
    "POOL_SIZE",
    "Texture",
    "get_texture",
    "pool_texture_ids",
    "smooth_noise",
]

PATTERNS = ("solid", "patches", "spots", "stripes", "band", "gradient")
NOISE_TERMS = 24  # cosines in each random smooth field
EDGE = 0.12  # soft-edge width of patches and stripes, in field std units
LOOK_ALIKE_PAIRS = ((1, 11), (9, 10), (4, 13))


def _smoothstep(x: Tensor) -> Tensor:
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _hash(cells: Tensor, salt: float) -> Tensor:
    """Pseudo-random numbers in [0, 1) per integer cell (N, 3) (float64 hash)."""
    v = cells @ torch.tensor([12.9898, 78.233, 37.719], dtype=torch.float64) + salt
    return torch.frac(torch.sin(v) * 43758.5453).abs()


@lru_cache(maxsize=4096)
def _wave_vectors(seed: int, name: str, scale: float) -> tuple[Tensor, Tensor]:
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])
    d = rng.normal(size=(3, NOISE_TERMS))
    d /= np.linalg.norm(d, axis=0, keepdims=True)
    freq = np.exp(rng.normal(0.0, 0.3, NOISE_TERMS)) / scale
    return (
        torch.as_tensor(2 * np.pi * d * freq, dtype=torch.float64),
        torch.as_tensor(rng.uniform(0, 2 * np.pi, NOISE_TERMS), dtype=torch.float64),
    )


def smooth_noise(points: Tensor, seed: int, name: str, scale: float) -> Tensor:
    """A smooth random field of zero mean and unit variance (a sum of random cosines).

    Args:
        points: (N, 3) (float64 recommended).
        seed, name: select the field (deterministically).
        scale: typical wavelength, in the units of ``points``.

    Returns:
        Field values, (N,) in the dtype of ``points``.
    """
    k, phase = _wave_vectors(int(seed), name, float(scale))
    return (
        torch.cos(points @ k.to(points.dtype) + phase.to(points.dtype)).sum(-1)
        * (2.0 / NOISE_TERMS) ** 0.5
    )


@dataclass(frozen=True, eq=False)
class Texture:
    """A procedural albedo on NNOPCS coordinates (see the module docstring).

    Attributes:
        texture_id: id in the pool (or generated).
        name: short description.
        base: base colour, RGB in [0, 1].
        pattern: one of :data:`PATTERNS`.
        secondary: pattern colour.
        scale: pattern wavelength / cell size, NNOPCS units.
        coverage: fraction of the surface in the secondary colour (patches,
            stripes, spots: probability that a cell holds a spot).
        axis: direction of stripes, bands and gradients.
        centre: position of a band along ``axis``.
        low: colour below NNOPCS height ``low_level`` (None: off).
        face: colour in front of NNOPCS x ``face_level`` (None: off).
        grain: amplitude of fine brightness noise.
        seed: seed of the random fields.
    """

    texture_id: int
    name: str
    base: tuple[float, float, float]
    pattern: str = "solid"
    secondary: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 0.3
    coverage: float = 0.4
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    centre: float = 0.5
    low: tuple[float, float, float] | None = None
    low_level: float = 0.3
    face: tuple[float, float, float] | None = None
    face_level: float = 0.8
    grain: float = 0.06
    seed: int = 0

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ConfigError(f"texture {self.texture_id}: unknown pattern {self.pattern!r}")

    def noise(self, p: Tensor, name: str, scale: float) -> Tensor:
        """:func:`smooth_noise` seeded by this texture."""
        return smooth_noise(p, self.seed, name, scale)

    # ------------------------------------------------------------------ pattern
    def pattern_weight(self, p: Tensor) -> Tensor:
        """Weight of the secondary colour at ``p`` (N, 3) float64 -> (N,) in [0, 1]."""
        if self.pattern == "solid":
            return torch.zeros(p.shape[0], dtype=p.dtype)
        threshold = float(np.sqrt(2.0) * _erfinv(1.0 - 2.0 * self.coverage))
        axis = torch.tensor(self.axis, dtype=p.dtype)
        axis = axis / axis.norm()
        if self.pattern == "patches":
            f = self.noise(p, "patches", self.scale)
            return _smoothstep((f - threshold) / EDGE + 0.5)
        if self.pattern == "stripes":
            warp = 0.6 * self.noise(p, "warp", 3.0 * self.scale)
            f = torch.sin(2 * np.pi * (p @ axis) / self.scale + 2.0 * warp) * 2**0.5
            return _smoothstep((f - threshold) / EDGE + 0.5)
        if self.pattern == "band":
            d = (p @ axis - self.centre).abs() + 0.02 * self.noise(p, "band", 0.1)
            return _smoothstep((self.scale / 2 - d) / 0.01 + 0.5)
        if self.pattern == "gradient":
            return _smoothstep((p @ axis - self.centre) / self.scale + 0.5)
        # spots: at most one disc per cell of a grid, kept inside its cell
        cells = torch.floor(p / self.scale)
        present = _hash(cells, self.seed * 1.37 + 0.1) < self.coverage
        radius = self.scale * (0.18 + 0.22 * _hash(cells, self.seed * 1.37 + 0.2))
        offset = torch.stack(
            [_hash(cells, self.seed * 1.37 + 0.3 + 0.1 * i) for i in range(3)], dim=-1
        )
        centre = (cells + 0.5) * self.scale + (offset - 0.5) * (self.scale - 2 * radius)[:, None]
        d = (p - centre).norm(dim=-1)
        return present * _smoothstep((radius - d) / (0.15 * radius) + 0.5)

    def __call__(self, nnopcs: Tensor) -> Tensor:
        """Albedo at NNOPCS points.

        Args:
            nnopcs: shape (N, 3) in [0, 1].

        Returns:
            RGB albedo in [0, 1], shape (N, 3), dtype of ``nnopcs``.
        """
        p = nnopcs.to(torch.float64)
        base = torch.tensor(self.base, dtype=p.dtype)
        w = self.pattern_weight(p)[:, None]
        colour = base + w * (torch.tensor(self.secondary, dtype=p.dtype) - base)
        if self.low is not None:
            wl = _smoothstep((self.low_level - p[:, 2]) / 0.03 + 0.5)[:, None]
            colour = colour + wl * (torch.tensor(self.low, dtype=p.dtype) - colour)
        if self.face is not None:
            wf = _smoothstep((p[:, 0] - self.face_level) / 0.03 + 0.5)[:, None]
            colour = colour + wf * (torch.tensor(self.face, dtype=p.dtype) - colour)
        if self.grain > 0:
            colour = colour * (1.0 + self.grain * self.noise(p, "grain", 0.04))[:, None]
        return colour.clamp(0.0, 1.0).to(nnopcs.dtype)

    def to_json(self) -> dict:
        out = {
            "texture_id": self.texture_id,
            "name": self.name,
            "base": list(self.base),
            "pattern": self.pattern,
        }
        if self.pattern != "solid":
            out |= {
                "secondary": list(self.secondary),
                "scale": self.scale,
                "coverage": self.coverage,
                "axis": list(self.axis),
                "centre": self.centre,
            }
        if self.low is not None:
            out |= {"low": list(self.low), "low_level": self.low_level}
        if self.face is not None:
            out |= {"face": list(self.face), "face_level": self.face_level}
        return out | {"grain": self.grain, "seed": self.seed}


def _erfinv(y: float) -> float:
    return float(torch.special.erfinv(torch.tensor(float(np.clip(y, -0.999999, 0.999999)))))


WHITE = (0.92, 0.91, 0.88)
BLACK = (0.07, 0.07, 0.07)

_POOL: tuple[dict, ...] = (
    dict(name="black patches on white (Holstein)", base=WHITE, pattern="patches",
         secondary=BLACK, scale=0.35, coverage=0.45, seed=100),
    dict(name="brown patches on white", base=WHITE, pattern="patches",
         secondary=(0.45, 0.25, 0.12), scale=0.3, coverage=0.4, seed=101),
    dict(name="solid black", base=(0.1, 0.1, 0.1), grain=0.1, seed=102),
    dict(name="cream with black freckles and black legs", base=(0.85, 0.8, 0.72),
         pattern="spots", secondary=BLACK, scale=0.035, coverage=0.35, low=BLACK,
         low_level=0.3, seed=103),
    dict(name="solid brown", base=(0.42, 0.24, 0.12), grain=0.08, seed=104),
    dict(name="dark spots on grey", base=(0.6, 0.6, 0.62), pattern="spots",
         secondary=(0.2, 0.2, 0.22), scale=0.09, coverage=0.6, seed=105),
    dict(name="red with white face and white underside (Hereford)", base=(0.55, 0.18, 0.1),
         low=WHITE, low_level=0.32, face=WHITE, face_level=0.78, seed=106),
    dict(name="black with a white belt (Belted Galloway)", base=BLACK, pattern="band",
         secondary=WHITE, scale=0.16, axis=(1.0, 0.0, 0.0), centre=0.5, seed=107),
    dict(name="dun with brown freckles", base=(0.76, 0.6, 0.4), pattern="spots",
         secondary=(0.3, 0.18, 0.08), scale=0.05, coverage=0.5, seed=108),
    dict(name="brindle", base=(0.42, 0.26, 0.12), pattern="stripes",
         secondary=(0.12, 0.08, 0.05), scale=0.08, coverage=0.45, axis=(0.3, 0.0, 1.0),
         seed=109),
    dict(name="brindle, look-alike of 9", base=(0.44, 0.27, 0.12), pattern="stripes",
         secondary=(0.14, 0.09, 0.05), scale=0.08, coverage=0.5, axis=(0.3, 0.0, 1.0),
         seed=109),
    dict(name="brown patches on white, look-alike of 1", base=WHITE, pattern="patches",
         secondary=(0.5, 0.27, 0.12), scale=0.3, coverage=0.4, seed=111),
    dict(name="roan (fine black and white mottling)", base=(0.8, 0.8, 0.82), pattern="patches",
         secondary=(0.15, 0.15, 0.18), scale=0.06, coverage=0.5, seed=112),
    dict(name="solid brown, look-alike of 4", base=(0.45, 0.26, 0.13), grain=0.08, seed=113),
    dict(name="dark back fading to a cream belly", base=(0.85, 0.75, 0.55), pattern="gradient",
         secondary=(0.3, 0.2, 0.12), scale=0.25, centre=0.55, axis=(0.0, 0.0, 1.0), seed=114),
    dict(name="large orange patches on white", base=WHITE, pattern="patches",
         secondary=(0.8, 0.45, 0.15), scale=0.6, coverage=0.3, seed=115),
)  # fmt: skip
POOL_SIZE = len(_POOL)


def pool_texture_ids() -> list[int]:
    """The ids of the fixed pool, ``0 .. POOL_SIZE - 1``."""
    return list(range(POOL_SIZE))


def _generated(texture_id: int) -> dict:
    """A random texture for an id outside the pool (deterministic in the id)."""
    rng = np.random.default_rng([texture_id, 0x7E57])

    def colour(dark: bool) -> tuple[float, float, float]:
        # natural coat colours: browns, blacks, creams, greys with a random tint
        v = rng.uniform(0.05, 0.35) if dark else rng.uniform(0.5, 0.95)
        tint = rng.uniform(-0.25, 0.25, 3) * v + np.array([0.12, 0.0, -0.1]) * v
        return tuple(np.clip(v + tint, 0.0, 1.0).round(4).tolist())

    pattern = str(rng.choice(PATTERNS))
    light_base = rng.random() < 0.5
    spec = dict(
        name=f"generated {pattern}",
        base=colour(dark=not light_base),
        pattern=pattern,
        secondary=colour(dark=light_base),
        coverage=float(rng.uniform(0.25, 0.6)),
        axis=tuple(rng.normal(size=3).round(4).tolist()),
        centre=float(rng.uniform(0.4, 0.6)),
        grain=float(rng.uniform(0.02, 0.1)),
        seed=int(texture_id),
    )
    spec["scale"] = float(
        {
            "patches": rng.uniform(0.08, 0.6),
            "spots": rng.uniform(0.03, 0.1),
            "stripes": rng.uniform(0.05, 0.15),
            "band": rng.uniform(0.1, 0.25),
            "gradient": rng.uniform(0.1, 0.4),
            "solid": 0.3,
        }[pattern]
    )
    if rng.random() < 0.25:
        spec |= {"low": colour(dark=rng.random() < 0.7), "low_level": float(rng.uniform(0.2, 0.35))}
    if rng.random() < 0.2:
        spec |= {"face": colour(dark=False), "face_level": float(rng.uniform(0.72, 0.82))}
    return spec


@lru_cache(maxsize=1024)
def get_texture(texture_id: int) -> Texture:
    """The texture with id ``texture_id`` (pool below :data:`POOL_SIZE`, generated above).

    Raises:
        ConfigError: a negative id.
    """
    texture_id = int(texture_id)
    if texture_id < 0:
        raise ConfigError(f"texture_ids: texture id must be >= 0, got {texture_id}")
    spec = _POOL[texture_id] if texture_id < POOL_SIZE else _generated(texture_id)
    return Texture(texture_id=texture_id, **spec)
