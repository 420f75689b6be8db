r"""A learned initialiser of inverse rendering: multi-view silhouettes -> 3D keypoints.

The cold start of :func:`netepu.geometry.inverse.invert_silhouettes` screens a library of
template poses at eight headings and optimises the best eight for 120 steps: most of its
time goes to telling starts apart. The initialiser predicts one start instead, from the
evidence the silhouettes give in 3D, so that a few refining steps of one start remain.

Input: the subject's visual hull around the triangulated centroid ``a`` of its silhouettes
(:func:`subject_volume`), a cube of :math:`G^3` voxels of half side ``extent`` body radii
``r``, its axes :math:`(e_1, e_2, u)` with :math:`u` the world's up
(:func:`nsd.ops.vectors.up_frame`). Two channels per voxel, over the views :math:`v` that
see it (it projects into the image, in front of the camera):

* the hull: 1 where every such view shows the subject *or an occluder* there (a pixel
  covered by another subject cannot carve), 0 elsewhere and where no view sees it;
* the share of those views whose silhouette holds it (occluders not counted).

Both are invariant to the cameras' number, placement and resolution, so one network serves
any calibrated rig.

Network (:class:`PoseInitialiser`): a 3D convolutional encoder-decoder (V2V-PoseNet's
shape, Moon et al. 2018, much smaller) to one heatmap per keypoint on a :math:`(G/2)^3`
grid, and the soft-argmax of each heatmap: keypoint :math:`k` at

.. math:: x_k = a + \mathrm{extent}\; r\; B \sum_j \mathrm{softmax}(h_k)_j\, g_j ,

:math:`g_j \in [-1, 1]^3` the heatmap cells' centres, :math:`B = (e_1, e_2, u)`. Turning a
body about the up axis turns its hull, so the network learns every heading from training
data that turns bodies at random (:mod:`netepu.geometry.initialiser_training`).
"""

from __future__ import annotations

import pickle
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from nsd.cameras.batch import CameraBatch
from nsd.cameras.projection import project_points
from nsd.ops.vectors import up_frame

__all__ = [
    "INITIALISER_FORMAT",
    "InitialiserConfig",
    "PoseInitialiser",
    "initial_keypoints",
    "load_initialiser",
    "subject_volume",
]

INITIALISER_FORMAT = "netepu-initialiser-v1"  # the checkpoint's "format"


@dataclass(frozen=True)
class InitialiserConfig:
    """What a :class:`PoseInitialiser` is (kept in its checkpoint).

    Attributes:
        n_keypoints: K.
        radius: body radius r of the species (scene units), the volume's unit.
        grid: voxels per side of the input volume, G (divisible by 8).
        extent: half side of the volume, body radii.
        width: channels of the first level (doubled at each of the three levels below).
        up: world up axis of the training world.
    """

    n_keypoints: int
    radius: float
    grid: int = 32
    extent: float = 1.4
    width: int = 16
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "up": list(self.up)}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> InitialiserConfig:
        return InitialiserConfig(**{**d, "up": tuple(float(x) for x in d["up"])})


@lru_cache(maxsize=4)
def _cell_centres(n: int) -> Tensor:
    """Centres of an n^3 grid over [-1, 1]^3, (n^3, 3) float64, first axis slowest (cached:
    do not modify)."""
    ax = (torch.arange(n, dtype=torch.float64) + 0.5) * (2.0 / n) - 1.0
    return torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)


def subject_volume(masks: Tensor, ignored: Tensor, camera: CameraBatch, anchor: Tensor,
                   cfg: InitialiserConfig) -> Tensor:
    """The initialiser's input: hull and view share of one subject around ``anchor``.

    Args:
        masks: the subject's silhouettes, (V, H, W) bool.
        ignored: pixels covered by other subjects (occluders), (V, H, W) bool.
        camera: the V views.
        anchor: the volume's centre, world (3,).
        cfg: grid, extent, radius and up.

    Returns:
        (2, G, G, G) float32: the module docstring's hull and share, axes :math:`(e_1, e_2, u)`.
    """
    V, H, W = masks.shape
    G = cfg.grid
    basis = up_frame(torch.tensor(cfg.up, dtype=torch.float64))
    pts = anchor.double() + (cfg.extent * cfg.radius) * _cell_centres(G) @ basis.T  # (M, 3)
    cams = CameraBatch.from_mapping(camera).to(torch.float64)
    uv, z = project_points(pts.expand(V, -1, -1), cams.K, cams.R, cams.t, cams.dist)
    u, v = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    seen = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)  # (V, M)
    pix = v.clamp(0, H - 1) * W + u.clamp(0, W - 1)
    inside = torch.gather(masks.flatten(1), 1, pix) & seen
    covered = torch.gather(ignored.flatten(1), 1, pix) & seen
    n_seen = seen.sum(0)
    hull = ((inside | covered | ~seen).all(0) & (n_seen > 0)).float()
    share = inside.sum(0).float() / n_seen.clamp(min=1).float()
    return torch.stack([hull, share]).reshape(2, G, G, G).float()


def _block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(c_in, c_out, 3, stride, 1, bias=False),
                         nn.GroupNorm(min(8, c_out // 4), c_out), nn.ReLU(inplace=True))


class PoseInitialiser(nn.Module):
    """Hull volume -> keypoints (module docstring).

    Shape:
        forward: (B, 2, G, G, G) -> (B, K, 3), in the volume's frame, units of ``extent``
        body radii (within [-1, 1]).
    """

    def __init__(self, cfg: InitialiserConfig) -> None:
        super().__init__()
        if cfg.grid % 8:
            raise ValueError(f"PoseInitialiser: grid must be divisible by 8, got {cfg.grid}")
        self.cfg = cfg
        w = cfg.width
        self.level1 = nn.Sequential(_block(2, w, 2), _block(w, w))  # G/2
        self.level2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))  # G/4
        self.level3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w))  # G/8
        self.up2 = _block(4 * w + 2 * w, 2 * w)
        self.up1 = _block(2 * w + w, w)
        self.heatmaps = nn.Conv3d(w, cfg.n_keypoints, 1)
        self.register_buffer("cells", _cell_centres(cfg.grid // 2).float(), persistent=False)

    def forward(self, volume: Tensor) -> Tensor:
        return torch.softmax(self.heatmap_logits(volume), -1) @ self.cells

    def heatmap_logits(self, volume: Tensor) -> Tensor:
        """(B, 2, G, G, G) -> the keypoints' heatmap logits (B, K, (G/2)^3) over ``cells``."""
        x1 = self.level1(volume)
        x2 = self.level2(x1)
        x3 = self.level3(x2)
        y = self.up2(torch.cat([F.interpolate(x3, scale_factor=2.0, mode="trilinear"), x2], 1))
        y = self.up1(torch.cat([F.interpolate(y, scale_factor=2.0, mode="trilinear"), x1], 1))
        return self.heatmaps(y).flatten(2)


@torch.no_grad()
def initial_keypoints(net: PoseInitialiser, masks: Tensor, ignored: Tensor,
                      camera: CameraBatch, anchor: Tensor) -> Tensor:
    """The initialiser's keypoints of one subject, world (K, 3) float32.

    Args: as :func:`subject_volume` (``anchor``: the triangulated centroid of ``masks``).
    """
    cfg = net.cfg
    vol = subject_volume(masks.bool(), ignored.bool(), camera, anchor, cfg)
    local = net(vol[None])[0].double()  # (K, 3)
    basis = up_frame(torch.tensor(cfg.up, dtype=torch.float64))
    return (anchor.double() + (cfg.extent * cfg.radius) * local @ basis.T).float()


def load_initialiser(path) -> PoseInitialiser:
    """A :class:`PoseInitialiser` from its checkpoint (``weights_only``).

    Raises:
        ValueError: not an initialiser checkpoint, or not a readable file.
    """
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, EOFError, RuntimeError, pickle.UnpicklingError) as e:
        raise ValueError(f"{path}: cannot be read as a checkpoint ({e.__class__.__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != INITIALISER_FORMAT:
        raise ValueError(f"{path}: not a NeTePu initialiser checkpoint ({INITIALISER_FORMAT})")
    net = PoseInitialiser(InitialiserConfig.from_dict(ckpt["config"]))
    net.load_state_dict(ckpt["state"])
    return net.eval()

