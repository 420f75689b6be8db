"""The hull-only decomposition: before this change, now, and each part of the change alone.

    git worktree add /tmp/hull-before 7d6630d    # the commit before (optional)
    .venv/bin/python tools/bench_hull.py --before /tmp/hull-before    # ~25 min on 2 cores
    .venv/bin/python tools/bench_hull.py --report hull_mixture    # ~25 min, alone
    .venv/bin/python tools/bench_hull.py --root /tmp/hull-scenes --report hull_blobs \
        --rules now "now, seeds by components (no blobs)" "now, every blob a seed"
    .venv/bin/python tools/bench_hull.py --root /tmp/hull-scenes --report hull_blobs_blind \
        --scenes <the five scenes of seeds 31-35> --rules now "now, seeds by components (no blobs)"
    .venv/bin/python tools/bench_hull.py --whole --frames 60 --before /tmp/hull-before \
        --root /tmp/hull-scenes --report hull_blob_penalty --rules now "now, no blob penalty"
    .venv/bin/python tools/bench_hull.py --whole --frames 60 --before /tmp/hull-before \
        --root /tmp/hull-scenes --report hull_cores --rules now "now, cores first on every rig"
    .venv/bin/python tools/bench_hull.py --whole --frames 60 --root /tmp/hull-scenes \
        --report hull_core_refits --scenes <the 12 scenes of 4 cameras> \
        --rules now "now, cores not refitted" "now, cores refitted twice"
    .venv/bin/python tools/bench_hull.py --whole --frames 60 --root /tmp/hull-scenes \
        --report hull_cores_rings --scenes <the 8 ring scenes of seeds 51-58> \
        --rules now "now, no cores first" "now, cores first on every rig"

The visual hull of the background residuals (:mod:`nsd.cues.occupancy`) places NSD's
windows, gives their depths and links the views at inference, and makes the training
priors; :mod:`nsd.evaluation.hull_baseline` scores it alone (no learning). Three rules
changed together:

* ``min_views``: a voxel is kept when a majority of the cameras see it (before: two);
* ``owner_radius``: a foreground pixel goes to the front-most individual with a voxel
  within 0.6 voxel sides (before: 1.5);
* ``clustering``: with the count known, a seeded k-means of the plane's columns (before:
  the ``k`` heaviest components, the largest bisected while fewer).

Later, the k-means gained a 3D Gaussian mixture that replaces it where it explains the
voxels better by ``inference.mixture_gain`` nats per voxel (bodies of unequal size).

Rows per scene: ``before`` (the given checkout of the commit before, scored in a
subprocess with its own code; left out without ``--before``), ``now`` (the defaults), and
``now`` with one rule put back (``min_views=2``, ``owner_radius=1.5``) or the seeds'
spread at 1.5 instead of 4, and the mixture never (``mixture_gain=inf``: the k-means
alone) or always (``-inf``), or each frame alone (``mixture_slack=-inf``: no frame's
Gaussians start the next's), or without the gate per scene (``mixture_scene_gain=-inf``:
each frame's mixture used where it gains ``mixture_gain``, whatever the scene's median
gain); these are the ``inference.mixture_*`` keys (:class:`nsd.cues.clustering.MixtureRules`);
or with the mixture's restarts run at every frame of a track (``RESTART_TOLERANCE=-inf``),
not only where the track's start is less likely than the partition's, or the k-means seeded
by components alone (``BLOB_GAP=0``: no blob seeds first) or by every blob, ghosts too
(``BLOB_SHARE=0``), or the mixture free to join blobs (``BLOB_PENALTY=0``), or the pixels
given to the front-most voxel whatever its place in its individual (``CORE_MAX_VIEWS=0``:
no cores first) or to the cores first on rigs of any size (``CORE_MAX_VIEWS`` unbounded),
with the cores cut from the Gaussian of all an individual's voxels (``CORE_REFITS=0``) or
from one estimated twice more from its core (``CORE_REFITS=2``),
or the gate per scene at its bound before 2026-11-30 (``mixture_scene_gain=0.03``).
``--whole`` scores frames spread over the whole recording instead of the held-out tail (the
hull needs no training); ``--every N`` every N-th frame of it.
``--rules`` keeps only the named rows; ``--root`` keeps the scenes (generated there once,
read again by later runs). Synthetic scenes of 2-6 individuals, 4-8 cameras,
apart and in contact (``nsd-synth``, seeds fixed), 30 held-out frames each, 128 x 128,
48^3 voxels, the shipped background estimate (``data.background``, as training and
``nsd-eval``); metrics as ``nsd-eval`` (nsd/evaluation/decomposition.py).

Writes ``docs/benchmarks/<--report>.{md,json}`` (default ``hull``; the mixture's rows:
``--report hull_mixture``; the track's: ``--report hull_track --rules now "now, k-means
only (no mixture)" "now, each frame alone (no track)"``; the gate's: ``--report hull_gate
--rules now "now, k-means only (no mixture)" "now, no gate per scene"``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.core.config import compose_app  # noqa: E402
from nsd.cues import clustering, occupancy  # noqa: E402
from nsd.cues.occupancy import hull_min_views, voxel_grid  # noqa: E402
from nsd.evaluation.hull_baseline import evaluate_hull  # noqa: E402
from nsd.io.ground_truth import GroundTruth  # noqa: E402
from nsd.io.scene_data import SceneData  # noqa: E402
from nsd.synth.scene import default_scene  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

BIN = Path(sys.executable).parent


def _huddle(n: int, species: str, radius: float, seed: int,
            *rig: str) -> tuple[int, list[str]]:
    """A huddle of ``n`` individuals of ``species`` (comma-separated) within ``radius``
    metres, its nsd-synth seed, 8 cameras unless ``rig`` overrides say otherwise."""
    return n, [f"num_individuals={n}", f"species=[{species}]", *(rig or ["rig.count=8"]),
               f"motion.area_radius={radius}", "motion.interaction=huddle", f"seed={seed}"]


SCENES = {  # name -> (individuals, nsd-synth overrides)
    "default scene (2 bipeds, 4 cameras)": (2, None),
    "2 bipeds huddling, 4 cameras": (
        2, ["num_individuals=2", "motion.interaction=huddle", "seed=1"]),
    "3 bipeds huddling, 4 cameras": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=1"]),
    "3 bipeds huddling, 4 cameras, seed 2": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=2"]),
    "3 bipeds free, 6-camera ring": (
        3, ["num_individuals=3", "rig.kind=ring", "rig.count=6", "motion.area_radius=2.5",
            "motion.interaction=free", "seed=4"]),
    "4 (bipeds, quadrupeds) huddling, 8 cameras": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0", "motion.interaction=huddle", "seed=1"]),
    "4 (bipeds, quadrupeds) huddling, 8 cameras, seed 3": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0", "motion.interaction=huddle", "seed=3"]),
    "4 quadrupeds huddling, 8 cameras": (
        4, ["num_individuals=4", "species=[quadruped]", "rig.count=8",
            "motion.area_radius=2.5", "motion.interaction=huddle", "seed=2"]),
    "3 (bipeds, quadrupeds) huddling, 6-camera ring": (
        3, ["num_individuals=3", "species=[quadruped,biped]", "rig.kind=ring", "rig.count=6",
            "motion.area_radius=2.0", "motion.interaction=huddle", "seed=5"]),
    "3 (2 quadrupeds, 1 biped) huddling, 8 cameras": (
        3, ["num_individuals=3", "species=[quadruped,biped]", "rig.count=8",
            "motion.area_radius=2.5", "motion.interaction=huddle", "seed=11"]),
    "5 (bipeds, quadrupeds) huddling, 8 cameras": (
        5, ["num_individuals=5", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=3.0", "motion.interaction=huddle", "seed=12"]),
    "4 (bipeds, quadrupeds) huddling, 8 cameras, seed 21": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0", "motion.interaction=huddle", "seed=21"]),
    "6 (bipeds, quadrupeds) huddling, 8 cameras": (
        6, ["num_individuals=6", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=3.0", "motion.interaction=huddle", "seed=22"]),
    "6 bipeds huddling, 8 cameras": (
        6, ["num_individuals=6", "rig.count=8", "motion.area_radius=2.0",
            "motion.interaction=huddle", "seed=1"]),
    # made after the blob seeds were chosen on the seed-21 group: their blind check
    "4 (bipeds, quadrupeds) huddling, 8 cameras, seed 31": _huddle(4, "biped,quadruped", 2.0, 31),
    "4 (bipeds, quadrupeds) huddling, 8 cameras, seed 32": _huddle(4, "biped,quadruped", 2.0, 32),
    "5 (bipeds, quadrupeds) huddling, 8 cameras, seed 33": _huddle(5, "biped,quadruped", 3.0, 33),
    "4 quadrupeds huddling, 8 cameras, seed 34": _huddle(4, "quadruped", 2.5, 34),
    "3 (2 quadrupeds, 1 biped) huddling, 6-camera ring, seed 35": _huddle(
        3, "quadruped,biped", 2.0, 35, "rig.kind=ring", "rig.count=6"),
    # tools/bench_contact.py's scenes made on 2026-11-30 after that day's defaults; the blob
    # penalty was found on the first (docs/nsd.md, "Why the group of seed 23 failed")
    "4 (bipeds, quadrupeds) huddling, 8 cameras, seed 23": _huddle(4, "biped,quadruped", 2.0, 23),
    "3 bipeds huddling, 4 cameras, seed 24": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=24"]),
    # made after the blob penalty was chosen: its blind check (the first three in nsd-synth's
    # default interaction, close: they approach and face each other)
    "4 (bipeds, quadrupeds) close, 8 cameras, seed 41": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0", "seed=41"]),
    "5 (bipeds, quadrupeds) close, 8 cameras, seed 42": (
        5, ["num_individuals=5", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.5", "seed=42"]),
    "3 (2 quadrupeds, 1 biped) close, 6-camera ring, seed 43": (
        3, ["num_individuals=3", "species=[quadruped,biped]", "rig.kind=ring", "rig.count=6",
            "motion.area_radius=2.0", "seed=43"]),
    "4 quadrupeds huddling, 8 cameras, seed 44": _huddle(4, "quadruped", 2.5, 44),
    # tools/bench_contact.py's scenes of one texture and of quadrupeds on 4 cameras (the same
    # nsd-synth overrides): the scenes where the per-scene gate's decision was looked at again
    "3 bipeds of one texture huddling, 4 cameras": (
        3, ["num_individuals=3", "texture_ids=[1,1,1]", "motion.interaction=huddle",
            "seed=1"]),
    "4 bipeds of one texture huddling, 4 cameras, seed 2": (
        4, ["num_individuals=4", "texture_ids=[7,7,7,7]", "motion.interaction=huddle",
            "seed=2"]),
    "2 quadrupeds of one texture huddling, 4 cameras, seed 4": (
        2, ["num_individuals=2", "species=[quadruped]", "texture_ids=[6,6]",
            "motion.interaction=huddle", "seed=4"]),
    "3 quadrupeds of one texture huddling, 4 cameras, seed 5": _huddle(
        3, "quadruped", 2.0, 5, "texture_ids=[6,6,6]"),
    "3 quadrupeds huddling, 4 cameras, seed 9": _huddle(3, "quadruped", 2.0, 9, "rig.count=4"),
    # rings of 5 cameras, where the cores' camera bound had not been measured, and rings of 4
    # and 6 beside them (the rigs above of 4 and 8 cameras are all corner rigs, of 6 rings)
    "3 bipeds huddling, 5-camera ring, seed 51": (
        3, ["num_individuals=3", "motion.interaction=huddle", "rig.kind=ring", "rig.count=5",
            "seed=51"]),
    "4 bipeds of one texture huddling, 5-camera ring, seed 52": (
        4, ["num_individuals=4", "texture_ids=[7,7,7,7]", "motion.interaction=huddle",
            "rig.kind=ring", "rig.count=5", "seed=52"]),
    "3 quadrupeds of one texture huddling, 5-camera ring, seed 53": _huddle(
        3, "quadruped", 2.0, 53, "texture_ids=[6,6,6]", "rig.kind=ring", "rig.count=5"),
    "4 (bipeds, quadrupeds) huddling, 5-camera ring, seed 54": _huddle(
        4, "biped,quadruped", 2.0, 54, "rig.kind=ring", "rig.count=5"),
    "3 quadrupeds huddling, 5-camera ring, seed 55": _huddle(
        3, "quadruped", 2.0, 55, "rig.kind=ring", "rig.count=5"),
    "3 bipeds huddling, 4-camera ring, seed 56": (
        3, ["num_individuals=3", "motion.interaction=huddle", "rig.kind=ring", "rig.count=4",
            "seed=56"]),
    "3 quadrupeds of one texture huddling, 4-camera ring, seed 57": _huddle(
        3, "quadruped", 2.0, 57, "texture_ids=[6,6,6]", "rig.kind=ring", "rig.count=4"),
    "4 bipeds of one texture huddling, 6-camera ring, seed 58": (
        4, ["num_individuals=4", "texture_ids=[7,7,7,7]", "motion.interaction=huddle",
            "rig.kind=ring", "rig.count=6", "seed=58"]),
}
METRICS = ("detection_rate", "mask_detection_rate", "mask_miou", "depth_order_accuracy",
           "association_accuracy", "merge_rate", "detection_rate_touching",
           "mask_detection_rate_touching", "mask_miou_touching", "touching_share")
# an older checkout's hull-only scores, with its own code and defaults (its grid knows no
# min_views; its evaluate_hull takes the same arguments)
BEFORE = """
import json, sys
import numpy as np, torch
sys.path.insert(0, sys.argv[1])
torch.set_num_threads(2)
from nsd.cues.occupancy import voxel_grid
from nsd.evaluation.hull_baseline import evaluate_hull
from nsd.io.ground_truth import GroundTruth
from nsd.io.scene_data import SceneData
data = SceneData(sys.argv[2], (128, 128), background=sys.argv[5])
idx = np.asarray(json.loads(sys.argv[4]))
m = evaluate_hull(data, idx, GroundTruth.load(sys.argv[2]), voxel_grid(data.rig, (128, 128), 48),
                  int(sys.argv[3]))
print(json.dumps(m))
"""


def scene_folder(root: Path, name: str) -> Path:
    """The folder of scene ``name`` of ``SCENES``: ``root/scene<i>`` (``i`` its place in
    ``SCENES``, the same whichever scenes are run), written by ``nsd-synth`` unless it is
    there already; the default scene is ``nsd-run``'s built-in one."""
    synth = SCENES[name][1]
    if synth is None:
        return default_scene()
    scene = root / f"scene{list(SCENES).index(name)}"
    if not (scene / "calibration.toml").exists():
        subprocess.run([str(BIN / "nsd-synth"), f"out={scene}", *synth], check=True,
                       capture_output=True)
    return scene


def _frames(data: SceneData, n: int, whole: bool = False, every: int = 0) -> np.ndarray:
    """``n`` frames spread evenly over the held-out tail, or over the whole recording; or
    every ``every``-th frame of the recording (``every`` > 0)."""
    if every > 0:
        return np.arange(0, len(data.frames), every)
    idx = np.asarray(data.heldout_frames if not whole else range(len(data.frames)))
    return idx[np.linspace(0, len(idx) - 1, n).round().astype(int)]


def _row(name: str, cameras: int, rule: str, m: dict, seconds: float, frames: int) -> dict:
    row = {"scene": name, "cameras": cameras, "rule": rule}
    row.update({key: m.get(key) for key in METRICS})
    row["s_per_frame"] = seconds / frames
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="frames scored per scene")
    ap.add_argument("--whole", action="store_true",
                    help="score frames spread over the whole recording instead of the "
                         "held-out tail (the hull needs no training)")
    ap.add_argument("--every", type=int, default=0,
                    help="score every N-th frame of the whole recording instead (N > 0; "
                         "--frames and --whole are then not read)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES),
                    help="scene names to run")
    ap.add_argument("--report", default="hull", help="docs/benchmarks/<report>.{md,json}")
    ap.add_argument("--rules", nargs="+", default=None,
                    help="only these rows (the rule names below; default: all)")
    ap.add_argument("--root", type=Path, default=None,
                    help="the folder of the scenes (default: a new temporary folder); "
                         "scenes already in it are not generated again")
    ap.add_argument("--before", type=Path, default=None,
                    help="a checkout of an older commit: its hull-only row per scene")
    args = ap.parse_args()
    torch.set_num_threads(2)
    root = args.root or Path(tempfile.mkdtemp(prefix="bench-hull-"))
    home = {"OWNER_RADIUS": occupancy, "SEED_SPREAD": clustering,
            "RESTART_TOLERANCE": clustering, "BLOB_GAP": clustering, "BLOB_SHARE": clustering,
            "BLOB_PENALTY": clustering, "CORE_MAX_VIEWS": occupancy,
            "CORE_REFITS": occupancy}
    shipped = clustering.MixtureRules.defaults()
    defaults = {key: getattr(module, key) for key, module in home.items()}
    background = str(compose_app("train").data.background)  # as training and nsd-eval
    rows = []
    for name in args.scenes:
        k = SCENES[name][0]
        scene = scene_folder(root, name)
        data = SceneData(scene, (128, 128), background=background)
        gt = GroundTruth.load(scene)
        idx = _frames(data, args.frames, args.whole, args.every)
        V = data.num_views
        if args.before:
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", BEFORE, str(args.before), str(scene),
                                  str(k), json.dumps(idx.tolist()), background],
                                 check=True, capture_output=True, text=True)
            m = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(_row(name, V, "before", m, time.perf_counter() - t0, len(idx)))
            print(rows[-1], flush=True)
        variants = [("now", "auto", {}), ("now, min_views=2", 2, {}),
                    ("now, owner_radius=1.5", "auto", {"OWNER_RADIUS": 1.5}),
                    ("now, seeds 1.5 radii apart", "auto", {"SEED_SPREAD": 1.5}),
                    ("now, k-means only (no mixture)", "auto", {"mixture_gain": np.inf}),
                    ("now, the mixture always", "auto", {"mixture_gain": -np.inf}),
                    ("now, each frame alone (no track)", "auto", {"mixture_slack": -np.inf}),
                    ("now, no gate per scene", "auto", {"mixture_scene_gain": -np.inf}),
                    ("now, restarts every frame", "auto", {"RESTART_TOLERANCE": -np.inf}),
                    ("now, seeds by components (no blobs)", "auto", {"BLOB_GAP": 0}),
                    ("now, every blob a seed", "auto", {"BLOB_SHARE": 0.0}),
                    ("now, no blob penalty", "auto", {"BLOB_PENALTY": 0.0}),
                    ("now, no cores first", "auto", {"CORE_MAX_VIEWS": 0}),
                    ("now, cores first on every rig", "auto", {"CORE_MAX_VIEWS": 10**6}),
                    ("now, cores not refitted", "auto", {"CORE_REFITS": 0}),
                    ("now, cores refitted twice", "auto", {"CORE_REFITS": 2}),
                    ("now, gate at 0.03", "auto", {"mixture_scene_gain": 0.03})]
        for rule, views, changed in variants:
            if args.rules is not None and rule not in args.rules:
                continue
            for key, value in defaults.items():  # module constants, read by the hull at each call
                setattr(home[key], key, changed.get(key, value))
            rules = clustering.MixtureRules.defaults(
                **{key: value for key, value in changed.items() if key not in home})
            grid = voxel_grid(data.rig, data.frame_hw, 48, min_views=views)
            t0 = time.perf_counter()
            m = evaluate_hull(data, idx, gt, grid, k, rules=rules)
            label = rule if rule != "now" else f"now (min_views {hull_min_views(V)})"
            rows.append(_row(name, V, label, m, time.perf_counter() - t0, len(idx)))
            print(rows[-1], flush=True)
        for key, value in defaults.items():
            setattr(home[key], key, value)
    span = ("frames spread over the whole recording" if args.whole else "held-out frames")
    span = (f"{args.frames} {span}" if args.every <= 0
            else f"one frame in {args.every} over the whole recording")
    before = ""
    if args.before:
        commit = subprocess.run(["git", "-C", str(args.before), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True).stdout.strip()
        before = f" (commit `{commit}`)" if commit else ""
    write_report(
        args.report, "The hull-only decomposition: before, now, and each rule put back", rows,
        notes=("Hull-only decomposition (nsd/evaluation/hull_baseline.py, no learning) of "
               f"{span} per scene at 128 x 128, 48^3 voxels, "
               f"background `{background}` (the shipped `data.background`). "
               f"`before`: the commit before the change{before}, its own code; `now`: a voxel kept "
               "when a majority of the cameras see it (`min_views`), a pixel owned by the "
               "front-most individual with a voxel within 0.6 voxel sides, the individuals "
               "by a k-means of the plane's columns seeded first by the heaviest component "
               f"of each blob (components joined across gaps of {2 * clustering.BLOB_GAP} "
               f"columns) scoring {clustering.BLOB_SHARE} of the mean per individual, then "
               "by components 4 typical radii apart, replaced by a 3D Gaussian mixture of "
               f"the voxels where it explains them better by {shipped.mixture_gain} nats "
               "per voxel, the previous scored frame's Gaussians one more start of it, "
               f"kept unless another is better by {shipped.mixture_slack}, tried only in "
               f"scenes where its median gain at {shipped.mixture_scene_sample} instants "
               f"spread over the scored frames reaches {shipped.mixture_scene_gain} (the "
               "`inference.mixture_*` keys), each fit paying "
               f"{clustering.BLOB_PENALTY} nats per voxel its labels hold outside their "
               "Gaussian's heaviest blob, and with at most "
               f"{occupancy.CORE_MAX_VIEWS} cameras a pixel given to the front-most voxel "
               "of the individuals' cores near it where there is one (voxels within "
               f"{occupancy.CORE_SPREAD} squared Mahalanobis distances of their "
               f"individual's Gaussian, estimated {occupancy.CORE_REFITS} more time(s) "
               "from its core) "
               "(nsd/cues/occupancy.py, nsd/cues/clustering.py), its 10 restarts run "
               "only where the carried start is less likely than the partition's by "
               f"more than {clustering.RESTART_TOLERANCE}; the other rows put one "
               "rule back, take the mixture never or always, each frame alone, no gate "
               "per scene, the restarts at every frame, seeds by components alone or by "
               "every blob, no blob penalty, no cores first, or the cores first on "
               "every rig, the cores from the Gaussian of all the voxels or refitted "
               "twice, or the gate at 0.03. Touching "
               "columns: instants where two individuals' amodal masks overlap in most "
               "cameras that see both (nsd/evaluation/contact.py). Scenes: `nsd-synth` with "
               "the overrides in tools/bench_hull.py (the default scene is `nsd-run`'s "
               "built-in one)."),
    )


if __name__ == "__main__":
    main()
