r"""Motion: gait cycles, gestures, random joint variation and root paths in a shared area.

Joint angles
    Per frame, the angles of an individual are the sum of

    * a **gait cycle** (:func:`gait_angles`): a biped walk (legs in
      anti-phase, arms swinging against the legs, knees flexing in swing) or a
      four-beat quadruped walk (left hind, left fore, right hind, right fore a
      quarter cycle apart). The gait phase advances by
      :math:`2\pi\,v\,\Delta t / \mathrm{stride}` so feet hardly slide, and the
      gait amplitude is the speed relative to the preferred speed;
    * **gestures** while standing: per standing bout, random targets for a few
      joints (a raised arm, a bent back, a turned head; a cow grazing or
      swishing its tail), smoothly blended in and out;
    * smooth **random variation** of every joint: two sinusoids of random
      frequency (0.1-0.6 Hz) and phase, with an amplitude proportional to the
      joint's range (``pose_variation``);

    and is then clamped to the species' joint limits. The height is set by
    :meth:`~nsd.synth.body.Individual.place_on_ground`.

Root paths
    Individuals alternate walking and standing bouts (exponential durations).
    While walking they steer towards a waypoint drawn uniformly in the disc of
    radius ``area_radius`` (a new one when it is reached), with an
    Ornstein-Uhlenbeck turn rate as noise, so they cover the whole area over
    time (a per-camera median background stays clean). With ``interaction:
    close`` all individuals share one waypoint, an individual left more than
    :attr:`MotionConfig.follow_gap` behind walks after the nearest other, and standing
    individuals turn to face the nearest other: overlaps in the images become
    frequent. With ``interaction: huddle`` the group alternates *huddles* and
    *dispersals* (exponential durations, means ``huddle_seconds`` and
    ``apart_seconds``): in a huddle every individual walks to one shared spot and
    stays in contact with the nearest other (a footprint gap of at most
    :data:`HUDDLE_GAP`; pairs groom, groups of 4-8 cluster), facing it; in a
    dispersal each wanders to its own waypoints, as with ``free``. With ``linger`` the
    first individual stays in place for that share of the recording before it moves.
    Individuals never interpenetrate: their ground footprints
    (capsules, :attr:`~nsd.synth.skeleton.Species.footprint`) are pushed apart
    (limbs may still touch).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.ops.vectors import wrap_angle
from nsd.synth.body import Individual, Pose
from nsd.synth.skeleton import Species

__all__ = [
    "INTERACTIONS",
    "MotionConfig",
    "Trajectory",
    "gait_angles",
    "sample_pose",
    "simulate_motion",
]

INTERACTIONS = ("free", "close", "huddle")
TURN_REVERSION = 1.0  # 1/s: mean reversion of the OU turn rate
SPEED_TAU = 0.5  # s: time constant of speed changes
GESTURE_TAU = 0.4  # s: time constant of gesture blending
STEER_GAIN = 2.5  # 1/s: turn rate per radian of heading error
SEPARATION_MARGIN = 0.05  # m kept between footprints
WAYPOINT_REACHED = 0.4  # m: a new waypoint is drawn within this distance of the current one
HUDDLE_GAP = 0.02  # m: in a huddle, an individual farther than this from all others joins them

# (joint, axis, low, high): gestures drawn per standing bout
GESTURES: dict[str, tuple[tuple[str, int, float, float], ...]] = {
    "biped": (
        ("left_shoulder", 1, -2.2, 0.2),
        ("left_shoulder", 0, 0.0, 1.3),
        ("left_elbow", 1, -2.0, 0.0),
        ("right_shoulder", 1, -2.2, 0.2),
        ("right_shoulder", 0, -1.3, 0.0),
        ("right_elbow", 1, -2.0, 0.0),
        ("spine", 1, -0.1, 0.6),
        ("spine", 2, -0.4, 0.4),
        ("neck_nose", 1, -0.4, 0.4),
        ("neck_nose", 2, -0.8, 0.8),
        ("left_hip", 1, -0.8, 0.1),
        ("right_knee", 1, 0.0, 1.2),
    ),
    "quadruped": (
        ("withers", 1, 0.0, 1.0),
        ("withers", 2, -0.5, 0.5),
        ("neck", 1, -0.3, 0.6),
        ("neck", 2, -0.5, 0.5),
        ("head", 2, -0.4, 0.4),
        ("tail_base", 2, -0.8, 0.8),
        ("tail_base", 1, 0.0, 0.5),
        ("front_left_knee", 1, 0.0, 1.0),
    ),
}


@dataclass(frozen=True)
class MotionConfig(ConfigSection):
    """Settings of :func:`simulate_motion` (see the module docstring).

    Attributes:
        interaction: ``free`` (independent wandering) or ``close`` (approach
            and face the nearest other individual).
        area_radius: radius of the shared disc, metres.
        walk_seconds: mean duration of a walking bout, s.
        stand_seconds: mean duration of a standing bout, s.
        speed_scale: multiplies each species' preferred walking speed.
        turn_noise: standard deviation of the stationary turn rate, rad/s.
        pose_variation: amplitude of the random joint variation (0: none).
        follow_gap: ``close``: an individual whose footprint is farther than this
            from every other's walks after the nearest, metres.
        huddle_seconds: ``huddle``: mean duration of a huddle (all in contact), s.
        apart_seconds: ``huddle``: mean duration of a dispersal between huddles, s.
        linger: share of the recording, from its start, during which the first
            individual stays where it is (standing, gesturing; a sleeping animal, a
            person at a bench): its pixels are then in most of the per-camera median
            backgrounds once ``linger`` > 0.5 (0: it moves like the others).
    """

    APP: ClassVar[str] = "synth"  # defaults: conf/synth.yaml, section `motion`
    KEY: ClassVar[str] = "motion"

    interaction: str
    area_radius: float
    walk_seconds: float
    stand_seconds: float
    speed_scale: float
    turn_noise: float
    pose_variation: float
    follow_gap: float
    huddle_seconds: float
    apart_seconds: float
    linger: float

    def validate(self) -> None:
        if self.interaction not in INTERACTIONS:
            raise ConfigError(
                f"motion.interaction: unknown value {self.interaction!r}; choose one of "
                f"{list(INTERACTIONS)}"
            )
        for key in ("area_radius", "walk_seconds", "stand_seconds", "huddle_seconds",
                    "apart_seconds"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"motion.{key}: must be > 0, got {getattr(self, key)}")
        for key in ("speed_scale", "turn_noise", "pose_variation", "follow_gap"):
            if getattr(self, key) < 0:
                raise ConfigError(f"motion.{key}: must be >= 0, got {getattr(self, key)}")
        if not 0 <= self.linger <= 1:
            raise ConfigError(f"motion.linger: must be in [0, 1], got {self.linger}")


@dataclass(frozen=True)
class Trajectory:
    """The poses of one individual over time.

    Attributes:
        poses: a :class:`~nsd.synth.body.Pose` batched over T frames (float64).
        walking: whether the individual is in a walking bout, bool (T,).
    """

    poses: Pose
    walking: np.ndarray

    def __len__(self) -> int:
        return len(self.poses)

    def pose_at(self, t: int) -> Pose:
        """The unbatched pose of frame ``t``."""
        return self.poses[t]


# ------------------------------------------------------------------ joint angles
def _idx(species: Species, name: str) -> int:
    return species.index(name)


def gait_angles(species: Species, phase: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
    """Joint angles of the species' walk cycle.

    Args:
        species: biped or quadruped.
        phase: gait phase, radians, (T,).
        amplitude: 0 (standing) .. ~1.2 (brisk walk), (T,).

    Returns:
        Joint angles, (T, K, 3) radians (not yet clamped).
    """
    phase, a = np.asarray(phase, float), np.asarray(amplitude, float)
    out = np.zeros((phase.size, species.num_keypoints, 3))

    def put(name: str, axis: int, value: np.ndarray) -> None:
        out[:, _idx(species, name), axis] += value

    if species.name == "biped":
        put("hip", 1, 0.05 * a)
        put("hip", 0, 0.04 * a * np.sin(phase))
        put("spine", 2, 0.08 * a * np.sin(phase))
        for side, leg_phase, other in (
            ("left", phase, phase + np.pi),
            ("right", phase + np.pi, phase),
        ):
            swing = np.maximum(0.0, np.cos(leg_phase)) ** 2
            put(f"{side}_hip", 1, -0.45 * a * np.sin(leg_phase))
            put(f"{side}_knee", 1, a * (0.1 + 0.95 * swing))
            put(f"{side}_foot", 1, 0.2 * a * np.sin(leg_phase) - 0.15 * a * swing)
            put(f"{side}_shoulder", 1, -0.35 * a * np.sin(other))
            put(f"{side}_shoulder", 0, 0.08 if side == "left" else -0.08)
            put(f"{side}_elbow", 1, -(0.2 + 0.3 * a))
        return out
    put("spine_mid", 0, 0.03 * a * np.sin(phase))
    put("withers", 1, 0.06 * a * np.sin(2 * phase))
    offsets = {"hind_left": 0.0, "front_left": 0.5, "hind_right": 1.0, "front_right": 1.5}
    for leg, off in offsets.items():
        lp = phase + off * np.pi
        swing = a * np.maximum(0.0, np.cos(lp)) ** 2
        if leg.startswith("front"):
            put(f"{leg}_shoulder", 1, -0.35 * a * np.sin(lp))
            put(f"{leg}_elbow", 1, -0.2 * swing)
            put(f"{leg}_knee", 1, 1.0 * swing)
            put(f"{leg}_hoof", 1, 0.5 * swing)
        else:
            put(f"{leg}_hip", 1, -0.35 * a * np.sin(lp))
            put(f"{leg}_stifle", 1, -0.5 * swing)
            put(f"{leg}_hock", 1, 0.9 * swing)
            put(f"{leg}_hoof", 1, 0.3 * swing)
    return out


def _joint_noise(
    species: Species, times: np.ndarray, rng: np.random.Generator, amount: float
) -> np.ndarray:
    """Smooth random joint variation, (T, K, 3) radians."""
    K = species.num_keypoints
    span = species.joint_limits[..., 1] - species.joint_limits[..., 0]
    out = np.zeros((times.size, K, 3))
    for _ in range(2):
        freq = rng.uniform(0.1, 0.6, (K, 3))
        ph = rng.uniform(0, 2 * np.pi, (K, 3))
        amp = amount * 0.06 * span * rng.uniform(0.5, 1.0, (K, 3))
        out += amp * np.sin(2 * np.pi * freq * times[:, None, None] + ph)
    return out


def _gesture_targets(species: Species, rng: np.random.Generator, amount: float) -> np.ndarray:
    """Random gesture offsets for one standing bout, (K, 3)."""
    target = np.zeros((species.num_keypoints, 3))
    for name, axis, lo, hi in GESTURES.get(species.name, ()):
        if rng.random() < 0.4 * min(1.0, amount):
            target[_idx(species, name), axis] += rng.uniform(lo, hi)
    return target


def _to_pose(individual: Individual, translation, heading, angles) -> Pose:
    pose = Pose(
        torch.as_tensor(np.asarray(translation), dtype=torch.float64),
        torch.as_tensor(np.asarray(heading), dtype=torch.float64),
        torch.as_tensor(np.asarray(angles), dtype=torch.float64),
    )
    return individual.place_on_ground(individual.clamp(pose))


def sample_pose(
    individual: Individual,
    rng: np.random.Generator,
    variation: float = 1.0,
    position: Sequence[float] = (0.0, 0.0),
    heading: float | None = None,
) -> Pose:
    """A random plausible pose: a random gait phase and amplitude, gestures and variation.

    For rendering single individuals in many poses (NeTePu-style training data).

    Args:
        individual: whose pose.
        rng: random generator.
        variation: amplitude of gestures and random joint offsets.
        position: ground position (x, y) of the body frame, metres.
        heading: radians; random when None.

    Returns:
        An unbatched float64 pose, clamped to the joint limits, standing on the ground.
    """
    sp = individual.species
    phase = rng.uniform(0, 2 * np.pi, 1)
    amp = rng.uniform(0.0, 1.2, 1)
    angles = gait_angles(sp, phase, amp)[0]
    if rng.random() < 0.5:
        angles += _gesture_targets(sp, rng, variation)
    span = sp.joint_limits[..., 1] - sp.joint_limits[..., 0]
    angles += variation * 0.12 * span * rng.uniform(-1, 1, span.shape)
    h = rng.uniform(-np.pi, np.pi) if heading is None else heading
    return _to_pose(individual, [position[0], position[1], 0.0], h, angles)


# ------------------------------------------------------------------ root paths
def _footprint(
    ind: Individual, pos: np.ndarray, heading: float
) -> tuple[np.ndarray, np.ndarray, float]:
    back, front, r = ind.species.footprint
    s = ind.proportions.scale
    back, front, r = back * s, front * s, r * s
    a, b = back + r, front - r
    if a > b:
        a = b = 0.5 * (back + front)
    f = np.array([np.cos(heading), np.sin(heading)])
    return pos + a * f, pos + b * f, r


def _closest_on_segments(p1, q1, p2, q2) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of two 2D segments."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    if a < 1e-12 and e < 1e-12:
        return p1, p2
    if a < 1e-12:
        return p1, p2 + np.clip(f / e, 0, 1) * d2
    c = d1 @ r
    if e < 1e-12:
        return p1 + np.clip(-c / a, 0, 1) * d1, p2
    b = d1 @ d2
    denom = a * e - b * b
    s = np.clip((b * f - c * e) / denom, 0, 1) if denom > 1e-12 else 0.0
    t = (b * s + f) / e
    if t < 0:
        t, s = 0.0, np.clip(-c / a, 0, 1)
    elif t > 1:
        t, s = 1.0, np.clip((b - c) / a, 0, 1)
    return p1 + s * d1, p2 + t * d2


def _gap(ind_i, pos_i, h_i, ind_j, pos_j, h_j) -> tuple[float, np.ndarray]:
    """Gap between two footprints (negative: overlap) and the unit direction j -> i."""
    a1, b1, r1 = _footprint(ind_i, pos_i, h_i)
    a2, b2, r2 = _footprint(ind_j, pos_j, h_j)
    c1, c2 = _closest_on_segments(a1, b1, a2, b2)
    d = c1 - c2
    n = np.linalg.norm(d)
    u = d / n if n > 1e-9 else np.array([1.0, 0.0])
    return n - r1 - r2, u


def _waypoint(config: MotionConfig, rng: np.random.Generator) -> np.ndarray:
    """A random point of the area (uniform in the disc of 0.85 x its radius)."""
    r = 0.85 * config.area_radius * np.sqrt(rng.random())
    a = rng.uniform(-np.pi, np.pi)
    return np.array([r * np.cos(a), r * np.sin(a)])


def _initial_positions(
    individuals: Sequence[Individual], config: MotionConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    N = len(individuals)
    pos, head = np.zeros((N, 2)), rng.uniform(-np.pi, np.pi, N)
    for i in range(N):
        for _ in range(2000):
            r = config.area_radius * 0.8 * np.sqrt(rng.random())
            a = rng.uniform(-np.pi, np.pi)
            pos[i] = (r * np.cos(a), r * np.sin(a))
            if all(
                _gap(individuals[i], pos[i], head[i], individuals[j], pos[j], head[j])[0]
                > SEPARATION_MARGIN
                for j in range(i)
            ):
                break
        else:
            raise ConfigError(
                f"motion.area_radius: {config.area_radius} m is too small to place {N} "
                "individuals without overlap; enlarge it"
            )
    return pos, head


def simulate_motion(
    individuals: Sequence[Individual],
    num_frames: int,
    fps: float,
    config: MotionConfig,
    rng: np.random.Generator,
) -> list[Trajectory]:
    """Simulate every individual's root path and joint angles (see the module docstring).

    Args:
        individuals: N individuals sharing the area.
        num_frames: T.
        fps: frames per second.
        config: the motion settings.
        rng: random generator (the only source of randomness).

    Returns:
        One :class:`Trajectory` (T frames) per individual.
    """
    config.validate()
    N, T, dt = len(individuals), int(num_frames), 1.0 / float(fps)
    pos, head = _initial_positions(individuals, config, rng)
    scale = np.array([i.proportions.scale for i in individuals])
    pref = (
        np.array(
            [i.species.walk_speed * config.speed_scale * rng.uniform(0.8, 1.1) for i in individuals]
        )
        * scale
    )
    stride = np.array(
        [i.species.stride_length * i.proportions.length_of("leg") for i in individuals]
    )
    walking = rng.random(N) < 0.6
    speed = np.where(walking, pref, 0.0)
    omega = np.zeros(N)
    phase = rng.uniform(0, 2 * np.pi, N)
    gestures = [_gesture_targets(i.species, rng, config.pose_variation) for i in individuals]
    gesture_now = [g.copy() for g in gestures]
    P, H, PH, A, WALK = (np.zeros((T, N, 2)), np.zeros((T, N)), np.zeros((T, N)),
                         np.zeros((T, N)), np.zeros((T, N), bool))  # fmt: skip
    G = [np.zeros((T, i.num_keypoints, 3)) for i in individuals]
    goals = np.stack([_waypoint(config, rng) for _ in range(N)])
    group_goal = _waypoint(config, rng)
    sigma = config.turn_noise * np.sqrt(2 * TURN_REVERSION)
    huddling = config.interaction == "huddle" and rng.random() < config.huddle_seconds / (
        config.huddle_seconds + config.apart_seconds
    )
    for t in range(T):
        P[t], H[t], PH[t], WALK[t] = pos, head, phase, walking
        A[t] = np.clip(speed / np.maximum(pref, 1e-6), 0.0, 1.2)
        for n in range(N):
            G[n][t] = gesture_now[n]
        # bouts
        switch = rng.random(N) < dt / np.where(walking, config.walk_seconds, config.stand_seconds)
        for n in np.flatnonzero(switch & walking):
            gestures[n] = _gesture_targets(individuals[n].species, rng, config.pose_variation)
        walking = walking ^ switch
        target_speed = np.where(walking, pref, 0.0)
        # steering: towards the waypoint while walking; close: face the nearest other
        omega += -TURN_REVERSION * omega * dt + sigma * np.sqrt(dt) * rng.normal(size=N)
        if config.interaction == "huddle" and rng.random() < dt / (
            config.huddle_seconds if huddling else config.apart_seconds
        ):
            huddling = not huddling
            group_goal = _waypoint(config, rng)
        close = config.interaction == "close" or huddling
        close = close and N > 1
        gap_limit = HUDDLE_GAP if huddling else config.follow_gap
        goal = np.repeat(group_goal[None], N, axis=0) if close else goals
        d = goal - pos
        steer = np.where(walking, STEER_GAIN * wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - head), 0.0)
        if close:
            for n in range(N):
                gap, m = min(
                    (_gap(individuals[n], pos[n], head[n], individuals[m], pos[m], head[m])[0], m)
                    for m in range(N)
                    if m != n
                )
                if gap > gap_limit:  # left behind: walk after the others
                    walking[n] = True
                    target_speed[n] = pref[n]
                    dm = pos[m] - pos[n]
                    steer[n] = STEER_GAIN * wrap_angle(np.arctan2(dm[1], dm[0]) - head[n])
                elif not walking[n]:  # standing: face the nearest other
                    dm = pos[m] - pos[n]
                    steer[n] = STEER_GAIN * wrap_angle(np.arctan2(dm[1], dm[0]) - head[n])
            reached = np.linalg.norm(pos - group_goal, axis=1).min() < WAYPOINT_REACHED + 0.3
            if reached and not huddling:  # a huddle stays where it formed
                group_goal = _waypoint(config, rng)
        else:
            for n in np.flatnonzero(np.linalg.norm(d, axis=1) < WAYPOINT_REACHED):
                goals[n] = _waypoint(config, rng)
        still = t < config.linger * T  # the first individual lingers where it is
        if still:
            walking[0], target_speed[0], speed[0], steer[0], omega[0] = False, 0.0, 0.0, 0.0, 0.0
        head = wrap_angle(head + (omega + steer) * dt)
        speed += (target_speed - speed) * min(1.0, dt / SPEED_TAU)
        step = speed * dt
        pos = pos + step[:, None] * np.stack([np.cos(head), np.sin(head)], axis=1)
        phase = phase + 2 * np.pi * step / stride
        for n in range(N):
            goal = gestures[n] if not walking[n] else 0.0 * gestures[n]
            gesture_now[n] += (goal - gesture_now[n]) * min(1.0, dt / GESTURE_TAU)
        # keep footprints apart and inside the area
        for _ in range(3):
            for n in range(N):
                for m in range(n + 1, N):
                    gap, u = _gap(individuals[n], pos[n], head[n], individuals[m], pos[m], head[m])
                    if gap < SEPARATION_MARGIN:
                        push = 0.5 * (SEPARATION_MARGIN - gap)
                        if still and n == 0:  # a lingering individual is not pushed
                            pos[m] -= 2 * push * u
                        else:
                            pos[n] += push * u
                            pos[m] -= push * u
        r = np.linalg.norm(pos, axis=1, keepdims=True)
        pos = np.where(r > config.area_radius, pos * config.area_radius / np.maximum(r, 1e-9), pos)
    times = np.arange(T) * dt
    out = []
    for n, ind in enumerate(individuals):
        sp = ind.species
        angles = gait_angles(sp, PH[:, n], A[:, n]) + G[n]
        angles += _joint_noise(sp, times, rng, config.pose_variation)
        translation = np.concatenate([P[:, n], np.zeros((T, 1))], axis=1)
        out.append(Trajectory(_to_pose(ind, translation, H[:, n], angles), WALK[:, n].copy()))
    return out
