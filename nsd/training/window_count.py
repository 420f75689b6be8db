"""How many windows NSD gets: ``model.num_windows``, chosen for the scene (``auto``) or checked.

NSD's windows are a fixed count (or, with presence learned, an upper bound) that the networks
are built with. Fewer windows than individuals each hold several bodies, more cut bodies in
pieces, in every camera alike, and no label-free figure of the run sees it (a consistent
merge looks like a good run: docs/nsd.md, "How many individuals the hull shows").

``model.num_windows: auto`` (the default) takes, before the networks are built,

1. the individuals the scene declares (``gt/scene.json`` of an ``nsd-synth`` scene: what a
   user who recorded three mice knows);
2. else, on footage long and wide enough to count (:func:`nsd.cues.count.countable`), the
   separate bodies its visual hull shows (:func:`nsd.cues.count.scene_bodies`; at least 1).
   The count is a lower bound: bodies that touch are one blob, so a pair that touches in
   nine frames of ten counts as one; a single performer given two windows is split between
   them in every camera alike (docs/pipeline.md, the Pose2Sim single-person demo);
3. else ``UNCOUNTED_WINDOWS``, the fixed default before ``auto``.

A number is kept as given and checked the same way: a count other than the declared one, or
below the bodies the hull shows, warns before training, naming the key to set.
"""

from __future__ import annotations

import logging

import numpy as np
from omegaconf import DictConfig

from nsd.cues.count import countable
from nsd.io.scene_data import SceneData
from nsd.model.bi_nvs import check_num_windows

__all__ = ["AUTO", "UNCOUNTED_WINDOWS", "hull_count_warning", "settle_window_count",
           "window_count_warning"]

log = logging.getLogger(__name__)

AUTO = "auto"
# auto's windows where nothing declares the count and the hull cannot count the bodies (too
# few frames or cameras): the fixed default before auto. (Where it counts, the hull's count:
# docs/benchmarks/hull_count.md, right on 21 of 24 scenes, fewer on 3, never more.)
UNCOUNTED_WINDOWS = 2


def window_count_warning(num_windows: int, presence: bool, individuals: int) -> str | None:
    """What is wrong with ``model.num_windows`` for a scene that declares how many
    individuals it holds (``gt/scene.json`` of an ``nsd-synth`` scene), or None.

    A fixed count (``presence`` off) must be the number of individuals: fewer windows each
    hold several bodies, more cut bodies in pieces, in every camera alike, which no
    label-free figure of the run can see. An upper bound (presence on) must not be below it.

        >>> window_count_warning(2, False, 2) is None, window_count_warning(6, True, 5) is None
        (True, True)
        >>> window_count_warning(2, False, 5)[:62]
        'model.num_windows=2 but the scene declares 5 individuals (gt/s'
    """
    if num_windows == individuals or (presence and num_windows > individuals):
        return None
    what = ("each window will hold several bodies" if num_windows < individuals else
            "the visual hull's clusters will cut bodies in pieces")
    return (f"model.num_windows={num_windows} but the scene declares {individuals} "
            f"individual{'s' * (individuals != 1)} (gt/scene.json): {what}; set "
            f"model.num_windows={individuals} or auto (nsd-run: train.model.num_windows)")


def hull_count_warning(num_windows: int, bodies: int, counts: np.ndarray) -> str | None:
    """What is wrong with ``model.num_windows`` for footage whose visual hull shows
    ``bodies`` separate bodies (:func:`nsd.cues.count.scene_bodies`, a lower bound on the
    individuals; ``counts`` per frame looked at), or None: more bodies than windows warn,
    fixed count or upper bound.

        >>> hull_count_warning(2, 2, np.array([1, 2, 2])) is None
        True
        >>> hull_count_warning(2, 4, np.array([2, 4, 4, 5]))[:63]
        'the visual hull shows 4 separate bodies in more than a tenth of'
    """
    if bodies <= num_windows:
        return None
    share = float(np.mean(counts > num_windows))
    return (f"the visual hull shows {bodies} separate bodies in more than a tenth of the "
            f"{len(counts)} frames looked at (more than {num_windows} in {share:.0%} of them), "
            f"more than model.num_windows={num_windows}: each window will hold several "
            f"bodies; set model.num_windows to the number of individuals, at least {bodies} "
            "(nsd-run: train.model.num_windows)")


def _hull_bodies(cfg: DictConfig, data: SceneData) -> tuple[int, np.ndarray]:
    """The visual hull's separate bodies and the per-frame counts, with the run's evidence
    and hull settings."""
    return data.hull_bodies(cfg.loss.evidence_threshold, cfg.loss.evidence_softness,
                            cfg.prior_proposal.resolution, cfg.prior_proposal.min_views)


def settle_window_count(cfg: DictConfig, data: SceneData, individuals: int | None,
                        scene: str = "") -> int:
    """``cfg.model.num_windows`` as a number: ``auto`` chosen for the scene (set in ``cfg``,
    so that the checkpoint keeps the number; logged with where it came from), a number
    checked (a warning where it cannot fit the scene).

    Args:
        cfg: nsd-train's config (``model``, ``loss``, ``prior_proposal``).
        data: the scene's frames (the visual hull is counted where nothing is declared).
        individuals: the individuals the scene declares (``gt/scene.json``), or None.
        scene: the scene's name, for the messages.

    Raises:
        ConfigError: ``num_windows`` neither ``auto`` nor an integer >= 1.
    """
    value = cfg.model.num_windows
    where = f"scene {scene}: " if scene else ""
    if value == AUTO:
        if individuals is not None:
            k, source = int(individuals), "the individuals the scene declares (gt/scene.json)"
        elif countable(data.frames.shape[0], data.num_views):
            bodies = _hull_bodies(cfg, data)[0]
            k = max(1, bodies)
            source = (f"the visual hull shows {bodies} separate bod{'ies' if bodies != 1 else 'y'}"
                      " (a lower bound: bodies that touch are one)")
        else:
            k, source = UNCOUNTED_WINDOWS, ("too few frames or cameras for the visual hull to "
                                            "count the bodies")
        cfg.model.num_windows = k
        log.info("%smodel.num_windows=auto: %d, %s; give the number of individuals "
                 "(model.num_windows=N) if you know it", where, k, source)
        return k
    check_num_windows(value)
    presence = bool(cfg.model.detector.presence)
    if individuals is not None:
        problem = window_count_warning(value, presence, individuals)
    elif countable(data.frames.shape[0], data.num_views):
        problem = hull_count_warning(value, *_hull_bodies(cfg, data))
    else:
        problem = None  # too short, or too few cameras, for the hull to count
    if problem:
        log.warning("%s%s", where, problem)
    return value
