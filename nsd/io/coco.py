"""A COCO JSON file written entry by entry, never held in memory as a whole.

Images and annotations are appended as JSON lines to two temporary files;
:meth:`CocoStreamWriter.close` concatenates them into one COCO dataset file::

    {"info": ..., "images": [...], "annotations": [...], "categories": [...]}

which ``pycocotools.coco.COCO(path)`` loads. Annotations get consecutive ids
from 1 (COCO requires them); the temporary files are removed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["CocoStreamWriter"]


class CocoStreamWriter:
    """Append COCO images and annotations; write the dataset file on :meth:`close`.

    Args:
        path: the ``.json`` file to write.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._parts = {k: self.path.with_name(f".{self.path.name}.{k}") for k in ("img", "ann")}
        self._files = {k: p.open("w", encoding="utf-8") for k, p in self._parts.items()}
        self.num_images = 0
        self.num_annotations = 0

    def add_image(self, image: Mapping[str, Any]) -> None:
        """Append one image entry (``id``, ``file_name``, ``width``, ``height``, ...)."""
        self._files["img"].write(json.dumps(dict(image)) + "\n")
        self.num_images += 1

    def next_annotation_id(self) -> int:
        """The id the next annotation will get."""
        return self.num_annotations + 1

    def add_annotation(self, ann: Mapping[str, Any]) -> int:
        """Append one annotation; its ``id`` is assigned here and returned."""
        ann_id = self.next_annotation_id()
        self._files["ann"].write(json.dumps({"id": ann_id, **ann}) + "\n")
        self.num_annotations += 1
        return ann_id

    def close(self, info: Mapping[str, Any], categories: Iterable[Mapping[str, Any]]) -> Path:
        """Write the dataset file and remove the temporary parts."""
        for f in self._files.values():
            f.close()
        with self.path.open("w", encoding="utf-8") as out:
            out.write('{"info": ' + json.dumps(dict(info)))
            for key, part in (("images", "img"), ("annotations", "ann")):
                out.write(f', "{key}": [')
                with self._parts[part].open(encoding="utf-8") as f:
                    for n, line in enumerate(f):
                        out.write(("," if n else "") + "\n" + line.rstrip("\n"))
                out.write("\n]")
            out.write(', "categories": ' + json.dumps([dict(c) for c in categories]) + "}\n")
        for p in self._parts.values():
            p.unlink()
        return self.path
