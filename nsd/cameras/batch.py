"""A batch of pinhole cameras as tensors: the form every batched projection reads.

:meth:`nsd.cameras.calibration.CameraRig.stacked` makes one from a rig (one entry per
view); indexing selects views, so ``cams[batch.view_v]`` are the cameras of a batch of
view pairs. Conventions are those of :mod:`nsd.cameras.projection`: world to camera
``x_c = R x_w + t``, pixels ``K [x_n; 1]`` with OpenCV distortion ``dist`` applied to the
normalised coordinates ``x_n`` (zero-padded to a length OpenCV supports).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["CameraBatch"]


@dataclass(frozen=True)
class CameraBatch:
    """B cameras.

    Attributes:
        K: intrinsics (B, 3, 3), pixels.
        R: world-to-camera rotations (B, 3, 3).
        t: world-to-camera translations (B, 3), the rig's unit.
        dist: OpenCV distortion coefficients (B, n); None: no distortion.

    Example:
        >>> cams = CameraBatch(torch.eye(3).expand(4, 3, 3), torch.eye(3).expand(4, 3, 3),
        ...                    torch.zeros(4, 3), torch.zeros(4, 5))
        >>> len(cams), cams[torch.tensor([0, 2])].K.shape, cams[1:2].dist.shape
        (4, torch.Size([2, 3, 3]), torch.Size([1, 5]))
    """

    K: Tensor
    R: Tensor
    t: Tensor
    dist: Tensor | None = None

    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, index: Any) -> CameraBatch:
        """The cameras at ``index`` (an int keeps a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return self.map(lambda x: x[index])

    def map(self, fn) -> CameraBatch:
        """``fn`` applied to every tensor (e.g. a dtype change, a repeat)."""
        return CameraBatch(
            fn(self.K), fn(self.R), fn(self.t), None if self.dist is None else fn(self.dist)
        )

    def to(self, *args: Any, **kwargs: Any) -> CameraBatch:
        """As :meth:`torch.Tensor.to` (dtype, device) for every tensor."""
        return self.map(lambda x: x.to(*args, **kwargs))

    def repeat(self, n: int) -> CameraBatch:
        """Every camera ``n`` times in a row: ``[c0 .. cB, c0 .. cB, ...]`` (B n cameras)."""
        return self.map(lambda x: x.repeat(n, *[1] * (x.dim() - 1)))

    @staticmethod
    def cat(batches: Sequence[CameraBatch]) -> CameraBatch:
        """The cameras of ``batches`` in order (all with or all without distortion)."""
        dists = [b.dist for b in batches]
        dist = None if any(d is None for d in dists) else torch.cat(dists)
        return CameraBatch(
            torch.cat([b.K for b in batches]),
            torch.cat([b.R for b in batches]),
            torch.cat([b.t for b in batches]),
            dist,
        )

    def as_dict(self) -> dict[str, Tensor]:
        """``{"K", "R", "t"[, "dist"]}`` for files (npz, checkpoints)."""
        out = {"K": self.K, "R": self.R, "t": self.t}
        if self.dist is not None:
            out["dist"] = self.dist
        return out

    @staticmethod
    def from_mapping(cameras: CameraBatch | Mapping[str, Any]) -> CameraBatch:
        """A batch from ``{"K", "R", "t"[, "dist"]}`` (tensors or arrays); a batch as is."""
        if isinstance(cameras, CameraBatch):
            return cameras
        missing = [k for k in ("K", "R", "t") if k not in cameras]
        if missing:
            raise ValueError(f"cameras need K, R and t; missing {missing}")
        dist = cameras.get("dist")
        return CameraBatch(
            torch.as_tensor(cameras["K"]),
            torch.as_tensor(cameras["R"]),
            torch.as_tensor(cameras["t"]),
            None if dist is None else torch.as_tensor(dist),
        )
