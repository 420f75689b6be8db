"""The synthetic multi-view world with full ground truth (see ``datasets/synthetic.md``).

Library API (everything works in memory; only :func:`write_scene` and
:func:`default_scene` touch the disk):

* :func:`make_individual` -> :class:`Individual` (species, proportions, texture),
  :meth:`Individual.keypoints3d`, :func:`sample_pose`, :func:`simulate_motion`;
* rigs: :func:`ring_rig`, :func:`nepumoo_rig`, :func:`corner_rig`, :func:`make_rig`;
* :func:`render_views`: images and every ground-truth map for V cameras;
* scenes: :class:`SceneConfig`, :func:`build_world`, :func:`write_scene`,
  :func:`default_scene`, :func:`tiny_config`; reading: :class:`SyntheticScene`.
"""

from nsd.synth.body import Individual, Pose, PosedBody, Proportions, make_individual
from nsd.synth.config import SceneConfig
from nsd.synth.groundtruth import SyntheticScene, load_dense
from nsd.synth.motion import MotionConfig, Trajectory, sample_pose, simulate_motion
from nsd.synth.nnopcs import nnopcs_bounds, nnopcs_of
from nsd.synth.raycast import ViewRays, camera_rays
from nsd.synth.render import render_views
from nsd.synth.rigs import corner_rig, look_at, make_rig, nepumoo_rig, ring_rig
from nsd.synth.scene import (
    SyntheticWorld,
    build_world,
    default_config,
    default_scene,
    tiny_config,
    write_scene,
)
from nsd.synth.skeleton import BIPED, QUADRUPED, SPECIES, Species, get_species
from nsd.synth.texture import LOOK_ALIKE_PAIRS, POOL_SIZE, Texture, get_texture

__all__ = [
    "BIPED",
    "LOOK_ALIKE_PAIRS",
    "POOL_SIZE",
    "QUADRUPED",
    "SPECIES",
    "Individual",
    "MotionConfig",
    "Pose",
    "PosedBody",
    "Proportions",
    "SceneConfig",
    "Species",
    "SyntheticScene",
    "SyntheticWorld",
    "Texture",
    "Trajectory",
    "ViewRays",
    "build_world",
    "camera_rays",
    "corner_rig",
    "default_config",
    "default_scene",
    "get_species",
    "get_texture",
    "load_dense",
    "look_at",
    "make_individual",
    "make_rig",
    "nepumoo_rig",
    "nnopcs_bounds",
    "nnopcs_of",
    "render_views",
    "ring_rig",
    "sample_pose",
    "simulate_motion",
    "tiny_config",
    "write_scene",
]
