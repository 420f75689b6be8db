"""``netepu-embed``: NeTePu texture codes of exported subjects, appended to the export's embeddings.

Reads an ``nsd-export`` folder (``crops/`` and ``embeddings.parquet``/``.npz``,
datasets/export.md), computes the texture code (:math:`\\mu`) of every crop
from its visible pixels only (:func:`netepu.texture.encoding.texture_codes`) and
appends it as a vector column (default ``texture``) to the embedding table,
row by row in the table's own order (rows are matched by annotation ``id``),
with :func:`nsd.io.embeddings.add_columns` (atomic).

Models that read NNOPCS need each subject's 3D keypoints and the cameras:
``keypoints`` is an ``.npz`` with ``id`` (n,) annotation ids and
``keypoints`` (n, K, 3) world keypoints (e.g. from NeTePu inverse rendering of
the multi-view masks), and ``calibration`` the scene's calibration file or
folder; the NNOPCS map is rendered at the crop pixels through the crop
window in native pixels. RGB-only models (``use_nnopcs: false``) need
neither. Rows without a crop or keypoints get NaN codes and a ``False`` in
``<column>_valid``. A third column, ``<column>_reid``, holds each code's
re-identification embedding (:meth:`netepu.texture.model.TextureModel.reid_embedding`:
the model's within-class whitening of the code, with ``reid_colour`` together with
the crop's colour statistics; the code itself for models without either): compare
individuals with it, render with ``<column>``.

Examples::

    netepu-embed export=exports/demo checkpoint=runs/netepu/texture/<run>/checkpoint.pt \\
        keypoints=exports/demo/keypoints3d.npz calibration=scenes/demo
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from netepu.texture.encoding import texture_codes
from netepu.texture.model import load_texture_model
from nsd.cameras.calibration_io import read_calibration
from nsd.core.app import check_command_line, reported
from nsd.core.atomic import atomic_save_npz, atomic_write_bytes
from nsd.core.device import call_on_device, resolve_device
from nsd.core.errors import ConfigError, NSDError
from nsd.core.threads import set_threads
from nsd.io.crops import read_crop_index, read_crops
from nsd.io.embeddings import add_columns, embeddings_path, read_embeddings

__all__ = ["embed_export", "embed_into_copy", "main", "write_surface_maps"]

log = logging.getLogger(__name__)
PROG = "netepu-embed"


def _keypoints(path: str | os.PathLike) -> dict[int, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"keypoints: {path} does not exist")
    with np.load(path) as z:
        if "id" not in z.files or "keypoints" not in z.files:
            raise ConfigError(
                f"keypoints: {path} must hold arrays 'id' (n,) and "
                f"'keypoints' (n, K, 3); it holds {z.files}"
            )
        ids, kps = z["id"], z["keypoints"]
    if kps.ndim != 3 or kps.shape[-1] != 3 or len(ids) != len(kps):
        raise ConfigError(
            f"keypoints: {path}: 'keypoints' must be (n, K, 3) with n = len(id), "
            f"got {kps.shape} for {len(ids)} ids"
        )
    return {int(i): k for i, k in zip(ids, kps, strict=True)}


def embed_export(
    export: str | os.PathLike,
    checkpoint: str | os.PathLike,
    keypoints: str | os.PathLike | None = None,
    calibration: str | os.PathLike | None = None,
    column: str = "texture",
    batch_size: int = 64,
    maps: str | os.PathLike | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """Append texture codes to an export's embedding table (see the module docstring).

    Args:
        maps: also write what the encoder read for every coded row to this ``.npz``
            (:func:`write_surface_maps`), and a grid image next to it.
        device: where the models run (a ``device`` setting, :mod:`nsd.core.device`).

    Returns:
        ``rows``, ``encoded`` (rows with a code), ``path`` of the table.
    """

    export = Path(export)
    table = embeddings_path(export)
    crops = export / "crops"
    if not (crops / "index.csv").is_file():
        raise ConfigError(
            f"export: {crops / 'index.csv'} does not exist (not an nsd-export folder with crops)"
        )
    texture, geometry, _ = load_texture_model(checkpoint)
    on = resolve_device(device)
    texture.to(on)
    geometry.to(on)
    kps, rig = _surface_inputs(texture, geometry, keypoints, calibration)
    index = {r["id"]: r for r in read_crop_index(crops)}
    row_ids = read_embeddings(table, columns=["id"])["id"].astype(np.int64)
    codes = np.full((len(row_ids), texture.cfg.latent), np.nan, np.float32)
    reid = np.full((len(row_ids), texture.cfg.reid_dims), np.nan, np.float32)
    cropped = [k for k, i in enumerate(row_ids) if int(i) in index]
    todo = [k for k in cropped if kps is None or int(row_ids[k]) in kps]
    if len(cropped) < len(row_ids):  # the export writes a crop for every row it keeps
        log.warning("%d of %d rows have no crop; their codes are NaN",
                    len(row_ids) - len(cropped), len(row_ids))
    if len(todo) < len(cropped):  # keypoints are fitted on every frame_step-th frame only
        log.info("%d of %d rows with a crop have no 3D keypoints (nsd-run fits them on every "
                 "netepu.keypoints.frame_step-th frame); their codes are NaN (nsd-run's "
                 "identities carry the coded rows' along each tracklet)",
                 len(cropped) - len(todo), len(cropped))
    read: dict[str, list] = {"id": [], "rgb": [], "inside": [], "surface": []}
    batch = _Batcher(texture, geometry, crops, index, kps, rig, calibration)
    for s in range(0, len(todo), batch_size):
        rows = todo[s : s + batch_size]
        got = batch.encode(rows, [int(row_ids[k]) for k in rows])
        if got is None:
            continue
        rows, ids, mu, rgb, inside, surface = got
        codes[rows] = mu.numpy()
        if maps is not None:
            read["id"] += ids
            read["rgb"].append(rgb.numpy())
            read["inside"].append(inside.numpy())
            if surface is not None:
                read["surface"].append(surface.numpy())
        reid[rows] = call_on_device(texture, texture.reid_embedding, mu, rgb, inside).numpy()
    valid = ~np.isnan(codes).any(1)
    if maps is not None:
        write_surface_maps(Path(maps), read, texture.cfg.crop_size)
    path = add_columns(table, {column: codes, f"{column}_valid": valid, f"{column}_reid": reid})
    return {"rows": len(row_ids), "encoded": int(valid.sum()), "path": str(path)}


def _surface_inputs(texture, geometry, keypoints, calibration) -> tuple[dict | None, Any]:
    """The keypoints (id -> (K, 3)) and calibration a model that reads NNOPCS maps needs."""
    if not texture.cfg.use_nnopcs:
        return None, None
    if keypoints is None or calibration is None:
        raise ConfigError(
            "this texture model reads NNOPCS maps: give keypoints=<npz with id, "
            "keypoints> and calibration=<scene calibration file or folder>"
        )
    kps = _keypoints(keypoints)
    rig = read_calibration(calibration)
    if kps and next(iter(kps.values())).shape[0] != geometry.n_keypoints:
        raise ConfigError(
            f"keypoints: {keypoints} has K = "
            f"{next(iter(kps.values())).shape[0]}, the model wants "
            f"{geometry.n_keypoints}"
        )
    return kps, rig


class _Batcher:
    """Texture codes of batches of an export's rows, from their crops (and keypoints)."""

    def __init__(self, texture, geometry, crops, index, kps, rig, calibration) -> None:
        self.texture, self.geometry, self.crops, self.index = texture, geometry, crops, index
        self.kps, self.rig, self.calibration = kps, rig, calibration
        self.cams = rig.stacked(torch.float32) if rig is not None else None

    def encode(self, rows: list[int], ids: list[int]):
        """(rows, ids, mu, rgb, inside, surface) of the rows whose crop mask is not empty."""
        images, masks = read_crops(self.crops, ids)
        keep = masks.reshape(len(ids), -1).any(1)
        if not keep.any():
            return None
        ids = [i for i, k in zip(ids, keep, strict=True) if k]
        rows = [r for r, k in zip(rows, keep, strict=True) if k]
        index = self.index
        window = torch.tensor(
            [[index[i]["crop_x"], index[i]["crop_y"], index[i]["crop_side"]] for i in ids],
            dtype=torch.float64,
        )
        kp = cam = None
        if self.texture.cfg.use_nnopcs:
            try:
                ci = torch.tensor([self.rig.index(index[i]["camera"]) for i in ids])
            except (KeyError, ValueError) as e:
                raise ConfigError(
                    f"calibration: {self.calibration} lacks a camera of the export: {e}"
                ) from e
            cam = self.cams[ci]
            kp = torch.from_numpy(np.stack([self.kps[i] for i in ids])).float()
        mu, rgb, inside, surface = call_on_device(
            self.texture,
            texture_codes,
            self.texture,
            self.geometry,
            torch.from_numpy(images[keep]),
            torch.from_numpy(masks[keep] > 0),
            kp,
            cam,
            window=window,
            return_crops=True,
        )
        return rows, ids, mu, rgb, inside, surface


def write_surface_maps(path: Path, read: dict[str, list], size: int, grid_rows: int = 12) -> None:
    """Write the encoder's crops of the coded rows and a grid a person can look at.

    ``<path>`` (``.npz``): ``id`` (n,) annotation ids, ``rgb`` (n, S, S, 3) uint8 masked
    crops, ``inside`` (n, S, S) bool, and for NNOPCS models ``nnopcs`` (n, S, S, 3) float16
    in [0, 1] (0 outside the mask) and, with normals, ``normals`` (n, S, S, 3) float16
    world normals. ``<path>.png``: up to ``grid_rows`` rows, each a crop, its NNOPCS map
    as colour and (with normals) its normals as colour.
    """

    n = len(read["id"])
    empty = np.zeros((0, size, size, 3), np.float32)
    rgb = np.concatenate(read["rgb"]) if n else empty
    inside = np.concatenate(read["inside"]) if n else np.zeros((0, size, size), bool)
    out = {"id": np.asarray(read["id"], np.int64), "inside": inside.astype(bool)}
    out["rgb"] = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    panels = [out["rgb"]]
    if read["surface"]:
        surface = np.concatenate(read["surface"])
        out["nnopcs"] = surface[..., :3].astype(np.float16)
        panels.append(np.round(np.clip(surface[..., :3], 0, 1) * 255).astype(np.uint8))
        if surface.shape[-1] == 6:
            out["normals"] = surface[..., 3:].astype(np.float16)
            shown = np.clip((surface[..., 3:] + 1) / 2, 0, 1) * inside[..., None]
            panels.append(np.round(shown * 255).astype(np.uint8))
    atomic_save_npz(path, **out)
    if n:
        pick = np.unique(np.linspace(0, n - 1, min(grid_rows, n)).round().astype(int))
        rows = [np.concatenate([p[i] for p in panels], 1) for i in pick]
        ok, buf = cv2.imencode(".png", cv2.cvtColor(np.concatenate(rows, 0), cv2.COLOR_RGB2BGR))
        if ok:
            atomic_write_bytes(path.with_suffix(".png"), buf.tobytes())


def embed_into_copy(
    export: str | os.PathLike,
    out: str | os.PathLike,
    checkpoint: str | os.PathLike,
    keypoints: str | os.PathLike | None = None,
    calibration: str | os.PathLike | None = None,
    maps: str | os.PathLike | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """:func:`embed_export` into a copy of the export's embedding table in folder ``out``.

    The export itself is left untouched: its table is copied to ``out`` and its
    ``crops/`` are linked there while the codes are computed.
    """

    export, out = Path(export), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = embeddings_path(export)
    shutil.copyfile(table, out / table.name)
    (out / "crops").symlink_to((export / "crops").resolve())
    try:
        return embed_export(out, checkpoint, keypoints, calibration, maps=maps, device=device)
    finally:
        (out / "crops").unlink()


@hydra.main(config_path="pkg://nsd.conf", config_name="netepu_embed", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    set_threads(int(cfg.threads))
    with reported(PROG):
        try:
            out = embed_export(cfg.export, cfg.checkpoint, cfg.keypoints, cfg.calibration,
                               cfg.column, int(cfg.batch_size), cfg.get("maps"), cfg.device)
        except (KeyError, ValueError) as e:  # a table or keypoint file of another layout
            if isinstance(e, NSDError):
                raise
            raise NSDError(f"export {cfg.export}: {e}") from e
        print(
            f"netepu-embed: {out['encoded']} of {out['rows']} rows encoded -> {out['path']} "
            f"(column '{cfg.column}')"
        )


def main() -> None:
    """Entry point of ``netepu-embed``; bad input exits with status 2 and one line."""
    check_command_line(PROG, "netepu_embed")
    _hydra_main()


if __name__ == "__main__":
    main()
