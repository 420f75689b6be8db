"""COCO ground truth of a synthetic scene: images, instance annotations, categories.

One COCO *image* per camera-frame; one *annotation* per individual per
camera-frame in which at least one of its pixels is visible. Masks are
run-length encoded with :mod:`pycocotools.mask` (``counts`` decoded to str),
so results exported by the toolkit can be scored with ``COCOeval``.

Annotation fields (COCO's, then ours)
    ``id``, ``image_id``, ``category_id`` (species), ``segmentation`` (the
    VISIBLE mask, RLE), ``area`` (visible pixels), ``bbox`` (visible box
    ``[x, y, w, h]``, pixel edges), ``iscrowd`` (0), ``keypoints``
    (``[x, y, v] * K``, pixel centres at integers; ``v`` = 0, 1, 2 as in
    :mod:`nsd.synth.render`, ``x = y = 0`` when ``v = 0``), ``num_keypoints``
    (keypoints with ``v > 0``); ``amodal_segmentation``, ``amodal_bbox``,
    ``amodal_area``, ``visible_fraction`` (visible / amodal pixels),
    ``identity_id``, ``texture_id``, ``depth`` (mean camera-space Z of the
    visible pixels, metres), ``root_depth`` (camera-space Z of keypoint 0).

Fully occluded individuals (amodal pixels but no visible one) are not in
``annotations`` (``COCOeval`` would count an empty mask as a target that can
never be found) but in ``occluded_annotations``, with the same fields and an
empty visible mask. Individuals entirely outside the image are omitted.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pycocotools import mask as mask_utils

from nsd.synth.body import Individual
from nsd.synth.skeleton import Species

__all__ = ["CocoBuilder", "encode_masks"]


def encode_masks(masks: np.ndarray) -> list[dict]:
    """RLE of boolean masks (N, H, W) with ``counts`` as str (JSON-ready)."""
    if masks.shape[0] == 0:
        return []
    rles = mask_utils.encode(np.asfortranarray(masks.transpose(1, 2, 0).astype(np.uint8)))
    for r in rles:
        r["counts"] = r["counts"].decode("ascii")
    return rles


def _xywh(box: np.ndarray) -> list[float]:
    x0, y0, x1, y1 = (float(v) for v in box)
    return [x0, y0, x1 - x0, y1 - y0]


class CocoBuilder:
    """Collects COCO images and annotations frame by frame.

    Args:
        species: the species present (one category each, id = ``category_id``).
        info: the ``info`` block.
    """

    def __init__(self, species: Sequence[Species], info: dict | None = None) -> None:
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        self.occluded: list[dict] = []
        uniq = {s.category_id: s for s in species}
        self.categories = [
            {
                "id": s.category_id,
                "name": s.name,
                "supercategory": "animal",
                "keypoints": list(s.keypoint_names),
                "skeleton": [[a + 1, b + 1] for a, b in s.skeleton],  # COCO: 1-based
                "kpt_oks_sigmas": list(s.kpt_oks_sigmas),
            }
            for _, s in sorted(uniq.items())
        ]
        self.info = info or {}
        self._next_ann = 1

    def add_image(
        self, image_id: int, file_name: str, size: tuple[int, int], camera: str, frame: int
    ) -> None:
        self.images.append(
            {
                "id": int(image_id),
                "file_name": file_name,
                "width": int(size[0]),
                "height": int(size[1]),
                "camera": camera,
                "frame": int(frame),
            }
        )

    def add_instances(
        self,
        image_id: int,
        individuals: Sequence[Individual],
        visible: np.ndarray,
        amodal: np.ndarray,
        boxes: np.ndarray,
        amodal_boxes: np.ndarray,
        depth: np.ndarray,
        keypoints2d: Sequence[np.ndarray],
        visibility: Sequence[np.ndarray],
        root_depth: Sequence[float],
    ) -> None:
        """Annotations of one camera-frame.

        Args:
            image_id: the COCO image.
            individuals: N individuals.
            visible, amodal: (N, H, W) bool.
            boxes, amodal_boxes: (N, 4) ``[x0, y0, x1, y1]``.
            depth: camera-space Z map (H, W), inf on background.
            keypoints2d: per individual (K_n, 2) pixels.
            visibility: per individual (K_n,) in {0, 1, 2}.
            root_depth: per individual, Z of keypoint 0.
        """
        vis_area = visible.reshape(visible.shape[0], -1).sum(1)
        am_area = amodal.reshape(amodal.shape[0], -1).sum(1)
        rles, am_rles = encode_masks(visible), encode_masks(amodal)
        for n, ind in enumerate(individuals):
            if am_area[n] == 0:
                continue
            v = np.asarray(visibility[n], dtype=np.int64)
            uv = np.where(v[:, None] > 0, np.asarray(keypoints2d[n], dtype=np.float64), 0.0)
            kps = np.concatenate([np.round(uv, 4), v[:, None]], axis=1).reshape(-1)
            z = depth[visible[n]]
            ann = {
                "id": self._next_ann,
                "image_id": int(image_id),
                "category_id": ind.species.category_id,
                "segmentation": rles[n],
                "area": int(vis_area[n]),
                "bbox": _xywh(boxes[n]),
                "iscrowd": 0,
                "keypoints": [float(x) if i % 3 < 2 else int(x) for i, x in enumerate(kps)],
                "num_keypoints": int((v > 0).sum()),
                "amodal_segmentation": am_rles[n],
                "amodal_bbox": _xywh(amodal_boxes[n]),
                "amodal_area": int(am_area[n]),
                "visible_fraction": round(float(vis_area[n]) / float(am_area[n]), 6),
                "identity_id": ind.identity,
                "texture_id": ind.texture_id,
                "depth": round(float(z.mean()), 6) if z.size else None,
                "root_depth": round(float(root_depth[n]), 6),
            }
            self._next_ann += 1
            (self.annotations if vis_area[n] > 0 else self.occluded).append(ann)

    def to_json(self) -> dict:
        return {
            "info": self.info,
            "images": self.images,
            "annotations": self.annotations,
            "occluded_annotations": self.occluded,
            "categories": self.categories,
        }
