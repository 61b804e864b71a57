"""Simulated Burger War matches (two TurtleBot3 burgers reading AR markers) as a Gymnasium env.

Registered ids (see ``zenrl.common.envs``): ``zenrl/BurgerWar-v0`` (vector observations) and
``zenrl/BurgerWarImage-v0`` (adds the robot's camera image). Full option list and layouts:
docs/burgerwar.md and :class:`BurgerWarEnv`.

Simulation: one pybullet DIRECT client per env; planar robots (prismatic x, prismatic y,
revolute yaw, all velocity-controlled) at ``physics_hz`` (60); the agent decides at
``control_hz`` (10); markers are read geometrically at ``capture_hz`` (10); the lidar is
computed analytically in numpy. Reset restores a state saved once after building the world.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Callable, Mapping, Sequence

import gymnasium as gym
import numpy as np
import pybullet as p
from gymnasium import spaces

from zenrl.common.guard_rule import GuardRule
from zenrl.games.burgerwar import geometry as geo
from zenrl.games.burgerwar.judge import BLUE, NEUTRAL, RED, Judge, match_outcome, robot_marker_points
from zenrl.games.burgerwar.opponents import OPPONENT_NAMES, OpponentView, make_opponent
from zenrl.games.burgerwar.render import TopDownRenderer

log = logging.getLogger(__name__)

SIDES = ("red", "blue")
#: the users' DQN actions (v m/s, w rad/s)
USERS_ACTIONS = ((0.2, 0.0), (-0.2, 0.0), (0.0, 0.0), (0.0, 0.5233), (0.0, -0.5233))
#: "rich": 3 speeds x 5 turn rates
RICH_ACTIONS = tuple((v, w) for v in (0.22, 0.0, -0.15) for w in (0.0, 0.5233, -0.5233, 1.4, -1.4))
REWARDS = ("users", "zero_sum", "sparse")


def spot_turns(table: Sequence[Sequence[float]]) -> tuple[int, int]:
    """``(left, right)``: the indices of the fastest turns on the spot (v = 0) of an action table
    of ``(v, w)`` rows, w > 0 turning left (the guard's turns). ValueError where the table has
    none in either direction."""
    left = max(((w, i) for i, (v, w) in enumerate(table) if v == 0 and w > 0), default=None)
    right = min(((w, i) for i, (v, w) in enumerate(table) if v == 0 and w < 0), default=None)
    if left is None or right is None:
        raise ValueError("the guard turns on the spot, and this action set has no such turn in both directions")
    return left[1], right[1]
MARKER_VALUES = ("unit", "points")
LIDAR_INVALID = ("clip", "zero", "inf")
#: AMCL's update thresholds in the contest kit's navigation bots (amcl.yaml: update_min_d,
#: update_min_a): the pose estimate is corrected after moving 0.1 m or turning 0.1 rad
AMCL_UPDATE = (0.1, 0.1)
#: the burger's acceleration limits in the contest kit's DWA planner parameters
#: (dwa_local_planner_params_burger.yaml: acc_lim_x 2.5 m/s^2, acc_lim_theta 3.0 rad/s^2)
BURGER_ACCEL = (2.5, 3.0)

# observation bounds
_SCORE_NORM = 10.0
_MAX_SCORE = int(geo.TARGET_POINTS[:geo.N_FIELD].sum() + geo.TARGET_POINTS[geo.RED_MARKERS].sum())


def _view_index(side: int) -> np.ndarray:
    """int[18]: target indices, in the order side ``side`` observes them (mask layout)."""
    field = np.arange(geo.N_FIELD) if side == 0 else geo.FIELD_MIRROR
    own, enemy = (geo.RED_MARKERS, geo.BLUE_MARKERS) if side == 0 else (geo.BLUE_MARKERS, geo.RED_MARKERS)
    return np.concatenate([field, own, enemy])


_VIEW_INDEX = (_view_index(0), _view_index(1))
#: owner code (0 neutral, 1 red, 2 blue) -> mask value (0 mine, 1 neutral, 2 enemy's)
_MASK_LUT = (np.array([1.0, 0.0, 2.0], np.float32), np.array([1.0, 2.0, 0.0], np.float32))


def _number(name: str, v) -> float:
    """``v`` as a float, or a ValueError naming the option."""
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None


def _pair(name: str, v) -> tuple[float, float]:
    """``v`` as two floats, or a ValueError naming the option."""
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair of numbers, got {v!r}") from None
    return a, b


def _clip(v, lim: float) -> float:
    v = float(v)
    return -lim if v < -lim else lim if v > lim else v


class BurgerWarEnv(gym.Env):
    """A Burger War match: the agent plays one side against a scripted or frozen opponent.

    Options (all keyword):
      image (False): add the camera image ``obs["image"]`` uint8[H, W, 3].
      image_size (64): int or (H, W) of the camera image.
      side ("red"): "red" | "blue" | "random" (drawn per episode). Observations are in the
        agent's own frame: blue sees the world rotated 180 deg, so one policy plays both sides.
      opponents ("teriyaki"): a name, a list of names (uniform) or a dict name -> weight; drawn
        per episode. Names: idle, random, cheese, teriyaki, clubhouse, waypoint, policy.
      opponent_policy (None): callable ``obs -> action`` for the "policy" opponent; it sees
        observations in its own frame and acts in this env's action space at ``control_hz``.
      control_hz (10): agent decisions per second (must divide physics_hz; 1 = the users' agent).
      physics_hz (60), capture_hz (10): physics rate and marker-reading (judge) rate.
      action_set ("users"): "users" (5 discrete), "rich" (15 discrete: v in {0.22, 0, -0.15} x
        w in {0, +-0.5233, +-1.4}) or "continuous" (Box [v, w] within +-0.22 m/s, +-2.84 rad/s).
      reward ("users"): "users" | "zero_sum" | "sparse" (see docs/burgerwar.md).
      read_range (0.8 m), read_angle (60 deg): geometric marker reading: camera-to-marker distance
        in [0.1, read_range], bearing within the camera's 0.864 rad FOV, angle between the
        marker's normal and the marker->camera direction below read_angle, and a clear 2D line of
        sight (boxes and the other robot block it). 0.8 m is the upper end of the estimated real
        range (reading works at ~0.3 m, fails beyond ~0.8-1.0 m); 60 deg is a typical AR-marker
        detection limit.
      lidar_noise (0.01): gaussian sigma (m) of the lidar, drawn from ``np_random``.
      privileged (False): add ``obs["enemy_pose"]`` float32[4] (x, y, cos, sin in own frame).
      enemy_detector (False): add ``obs["enemy_seen"]`` float32[3] (seen, x forward, y left of
        the robot, m): the other robot as a detector on the robot's own lidar scan finds it
        (:func:`~zenrl.games.burgerwar.geometry.detect_circle`: in line of sight and range, its
        position from the noisy readings; zeros when not seen). Not privileged: the scan holds
        it, this names it, as contest teams' enemy detectors do.
      flatten_obs (False): one float32 vector (lidar, pose, mask, game[, enemy_pose][,
        enemy_seen]); vector variant only.
      match_time (180), sudden_death_time (60), call_diff (10): judge rules.
      win_bonus (5.0): terminal +-bonus of the zero_sum reward.
      face_penalty (0.0), face_radius (1.2 m), face_angle (15 deg): a shaping term added to any
        reward (component ``facing``): ``face_penalty`` (<= 0) on each step that ends with the
        other robot seen by the enemy detector (needs ``enemy_detector``) nearer than
        ``face_radius`` and more than ``face_angle`` off the heading, where its camera can reach
        the robot's side and back markers: a push towards facing a robot that comes close
        (docs/burgerwar.md, "Rewards"); 0 leaves the reward as it was.
      wall_dist (0.2 m), wall_penalty (-0.5), far_dist (1.0 m), far_penalty (-0.5): the users'
        reward penalties (robot closer than wall_dist to the arena wall; farther than far_dist
        from the centre).
      start_noise (0.0): sigma (m, and rad x 2) of a gaussian jitter of the start poses.
      marker_values ("unit"): "unit" (the users' reward: every marker +-1) or "points" (each
        marker worth its points: field 1, robot side 3, back 5); users' reward only.
      lidar_invalid ("clip"): what the observed lidar shows for a reading outside 0.12-3.5 m:
        "clip" (clipped into the range), "zero" (0.0, the real LDS-01 driver) or "inf" (inf,
        the Gazebo sensor). lidar_dropout (0.0): probability that a beam reads invalid anyway
        ("zero"/"inf" only). Scripted opponents always see the clipped scan.
      pose_noise (0.0), pose_noise_yaw (0.0), pose_update ((0.1, 0.1)): AMCL-like error of the
        observed pose: a gaussian offset (sigma m, rad) held until the robot has moved
        pose_update[0] m or turned pose_update[1] rad since the last draw (AMCL's update_min_d,
        update_min_a), then drawn anew.
      accel_limit (None): (m/s^2, rad/s^2) acceleration limits of both robots (the commanded
        speeds ramp at most this fast; e.g. BURGER_ACCEL); None = speed changes at once.
      render_mode (None | "rgb_array"), render_size (256): top-down numpy rendering.
      max_steps (None): truncate after that many agent steps (the match ends by itself).

    Observation (Dict, own frame): ``lidar`` float32[360] (0.12-3.5 m, index 0 forward, CCW),
    ``pose`` float32[4] (x, y, cos yaw, sin yaw), ``mask`` float32[18] (12 field markers, my 3
    (L, R, B), enemy's 3 (L, R, B); 0 mine, 1 neutral, 2 enemy's), ``game`` float32[4]
    (time / match_time, sudden-death flag, my score / 10, enemy score / 10), optional
    ``enemy_pose``, ``enemy_seen`` and ``image``.

    info: ``war_state`` (the judge's JSON shape), ``captures`` (events this step),
    ``winner`` ("r"/"b"/"draw"/None), ``reward_components``, ``side``, ``opponent``; on the step
    that ends the match (``terminated``, or ``truncated`` by ``max_steps``) also ``outcome``
    ("win" | "draw" | "loss" from the agent's side, :func:`~zenrl.games.burgerwar.judge.match_outcome`),
    ``my_score`` and ``enemy_score`` (ints), and ``my_robot_points`` / ``enemy_robot_points``:
    the part of each score read from the other robot's markers
    (:func:`~zenrl.games.burgerwar.judge.robot_marker_points`). Generic code (``EnvBatch``, the
    evaluator) learns a match's result from these keys alone; a match cut off by an outer
    TimeLimit wrapper has not finished and has none.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, *, image: bool = False,
                 image_size: int | Sequence[int] = 64, side: str = "red",
                 opponents: str | Sequence[str] | Mapping[str, float] = "teriyaki",
                 opponent_policy: Callable[[Any], Any] | None = None, control_hz: int = 10,
                 physics_hz: int = 60, capture_hz: int = 10, action_set: str = "users",
                 reward: str = "users", read_range: float = 0.8, read_angle: float = 60.0,
                 lidar_noise: float = 0.01, privileged: bool = False, enemy_detector: bool = False,
                 flatten_obs: bool = False,
                 match_time: float = 180.0, sudden_death_time: float = 60.0, call_diff: int = 10,
                 win_bonus: float = 5.0, face_penalty: float = 0.0, face_radius: float = geo.GUARD_RADIUS_M,
                 face_angle: float = geo.GUARD_ANGLE_DEG, wall_dist: float = 0.2, wall_penalty: float = -0.5,
                 far_dist: float = 1.0, far_penalty: float = -0.5, start_noise: float = 0.0,
                 render_size: int = 256, max_steps: int | None = None,
                 marker_values: str = "unit", lidar_invalid: str = "clip",
                 lidar_dropout: float = 0.0, pose_noise: float = 0.0, pose_noise_yaw: float = 0.0,
                 pose_update: Sequence[float] = AMCL_UPDATE,
                 accel_limit: Sequence[float] | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unsupported render_mode {render_mode!r}")
        if side not in ("red", "blue", "random"):
            raise ValueError("side must be 'red', 'blue' or 'random'")
        if reward not in REWARDS:
            raise ValueError(f"reward must be one of {REWARDS}")
        if flatten_obs and image:
            raise ValueError("flatten_obs is only available for the vector variant")
        self._check_conventions(reward, marker_values, lidar_invalid, lidar_dropout, pose_noise,
                                pose_noise_yaw, pose_update, accel_limit)
        for name, hz in (("control_hz", control_hz), ("capture_hz", capture_hz)):
            if hz <= 0 or physics_hz % hz:
                raise ValueError(f"{name}={hz} must divide physics_hz={physics_hz}")
        self.render_mode = render_mode
        self.image = bool(image)
        self.image_hw = (int(image_size), int(image_size)) if np.isscalar(image_size) else tuple(
            int(s) for s in image_size)
        self.side_option = side
        self.opponent_policy = opponent_policy
        self.control_hz, self.physics_hz, self.capture_hz = int(control_hz), int(physics_hz), int(capture_hz)
        self.action_set = action_set
        self.reward_mode = reward
        self.read_range = float(read_range)
        self.read_angle = float(read_angle)
        self._cos_read = math.cos(math.radians(read_angle))
        self.lidar_noise = float(lidar_noise)
        self.privileged = bool(privileged)
        self.enemy_detector = bool(enemy_detector)
        self.flatten_obs = bool(flatten_obs)
        self.win_bonus = float(win_bonus)
        self.face_penalty, self.face_radius = float(face_penalty), float(face_radius)
        if not (math.isfinite(self.face_penalty) and self.face_penalty <= 0.0):
            raise ValueError(f"face_penalty must be a finite number <= 0 (got {face_penalty!r})")
        if self.face_penalty and not enemy_detector:
            raise ValueError("face_penalty needs enemy_detector=True: it is paid on what the detector sees")
        if not (math.isfinite(self.face_radius) and self.face_radius > 0.0 and 0.0 <= float(face_angle) < 180.0):
            raise ValueError(f"face_radius must be > 0 m and face_angle in [0, 180) degrees "
                             f"(got {face_radius!r}, {face_angle!r})")
        self._face_cos = math.cos(math.radians(float(face_angle)))
        self._agent_seen = np.zeros(3, np.float32)
        # one rule for the facing term and the guard; no turns (-1) for the continuous action set
        table = self.action_table
        self._guard = GuardRule(self.face_radius, self._face_cos, *(spot_turns(table) if table else (-1, -1)))
        self.wall_dist, self.wall_penalty = float(wall_dist), float(wall_penalty)
        self.far_dist, self.far_penalty = float(far_dist), float(far_penalty)
        self.start_noise = float(start_noise)
        self.max_steps = max_steps
        self.marker_values = marker_values
        self._marker_weights = (geo.TARGET_POINTS.astype(np.float64) if marker_values == "points"
                                else np.ones(geo.N_TARGETS))
        self.lidar_invalid = lidar_invalid
        self.lidar_dropout = float(lidar_dropout)
        self._lidar_fill = {"zero": 0.0, "inf": np.inf}.get(lidar_invalid)
        self.pose_noise, self.pose_noise_yaw = float(pose_noise), float(pose_noise_yaw)
        self.pose_update = (float(pose_update[0]), float(pose_update[1]))
        self.accel_limit = None if accel_limit is None else (float(accel_limit[0]), float(accel_limit[1]))
        self.judge = Judge(match_time, sudden_death_time, call_diff)

        # opponents
        if isinstance(opponents, str):
            names, weights = [opponents], [1.0]
        elif isinstance(opponents, Mapping):
            names, weights = list(opponents), [float(w) for w in opponents.values()]
        else:
            names, weights = list(opponents), [1.0] * len(opponents)
        for n in names:
            if n not in OPPONENT_NAMES:
                raise ValueError(f"unknown opponent {n!r}; known: {OPPONENT_NAMES}")
        wsum = float(sum(weights))
        if not names or wsum <= 0:
            raise ValueError("opponents must name at least one opponent with positive weight")
        self._opp_names = names
        self._opp_probs = np.array(weights) / wsum
        self._opps = {n: make_opponent(n, opponent_policy, control_hz) for n in names}

        # actions
        if action_set == "users":
            self._actions = np.array(USERS_ACTIONS)
            self.action_space = spaces.Discrete(len(USERS_ACTIONS))
        elif action_set == "rich":
            self._actions = np.array(RICH_ACTIONS)
            self.action_space = spaces.Discrete(len(RICH_ACTIONS))
        elif action_set == "continuous":
            self._actions = None
            self.action_space = spaces.Box(np.array([-geo.MAX_V, -geo.MAX_W], np.float32),
                                           np.array([geo.MAX_V, geo.MAX_W], np.float32))
        else:
            raise ValueError("action_set must be 'users', 'rich' or 'continuous'")

        self.observation_space = self._make_obs_space()
        self._lidar = geo.Lidar()
        self._renderer: TopDownRenderer | None = None
        self.render_size = int(render_size)
        self._sub = self.physics_hz // self.control_hz
        self._cap_every = self.physics_hz // self.capture_hz
        self._client = -1
        self._build_world()

    @staticmethod
    def _check_conventions(reward, marker_values, lidar_invalid, lidar_dropout, pose_noise,
                           pose_noise_yaw, pose_update, accel_limit) -> None:
        """The contestants' conventions (marker points, lidar, AMCL pose, acceleration)."""
        if marker_values not in MARKER_VALUES:
            raise ValueError(f"marker_values must be one of {MARKER_VALUES}, got {marker_values!r}")
        if marker_values != "unit" and reward != "users":
            raise ValueError(f"marker_values={marker_values!r} applies to reward='users' only, "
                             f"got reward={reward!r}")
        if lidar_invalid not in LIDAR_INVALID:
            raise ValueError(f"lidar_invalid must be one of {LIDAR_INVALID}, got {lidar_invalid!r}")
        if not 0.0 <= _number("lidar_dropout", lidar_dropout) < 1.0:
            raise ValueError(f"lidar_dropout must be in [0, 1), got {lidar_dropout!r}")
        if float(lidar_dropout) > 0 and lidar_invalid == "clip":
            raise ValueError("lidar_dropout needs lidar_invalid='zero' or 'inf' (a dropped beam "
                             "reads invalid), got lidar_invalid='clip'")
        for name, v in (("pose_noise", pose_noise), ("pose_noise_yaw", pose_noise_yaw)):
            if not _number(name, v) >= 0:
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        if not all(v > 0 for v in _pair("pose_update", pose_update)):
            raise ValueError(f"pose_update must be (metres > 0, radians > 0), got {pose_update!r}")
        if accel_limit is not None and not all(v > 0 for v in _pair("accel_limit", accel_limit)):
            raise ValueError(f"accel_limit must be None or (m/s^2 > 0, rad/s^2 > 0), got {accel_limit!r}")

    # ------------------------------------------------------------------------- spaces
    def _make_obs_space(self) -> spaces.Space:
        h = geo.ARENA_HALF_DIAG
        jt = self.judge
        tmax = (jt.match_time + jt.sudden_death_time) / jt.match_time
        smax = _MAX_SCORE / _SCORE_NORM
        parts = {
            "lidar": (np.full(geo.LIDAR_BEAMS, geo.LIDAR_MIN if self._lidar_fill != 0.0 else 0.0),
                      np.full(geo.LIDAR_BEAMS, geo.LIDAR_MAX if self._lidar_fill != np.inf else np.inf)),
            "pose": (np.array([-h, -h, -1, -1]), np.array([h, h, 1, 1])),
            "mask": (np.zeros(geo.N_TARGETS), np.full(geo.N_TARGETS, 2.0)),
            "game": (np.zeros(4), np.array([tmax, 1.0, smax, smax])),
        }
        if self.privileged:
            parts["enemy_pose"] = parts["pose"]
        if self.enemy_detector:
            m = geo.LIDAR_MAX + 2 * geo.HOUSING_R
            parts["enemy_seen"] = (np.array([0.0, -m, -m]), np.array([1.0, m, m]))
        if self.flatten_obs:
            self._flat_keys = list(parts)
            lo = np.concatenate([parts[k][0] for k in parts]).astype(np.float32)
            hi = np.concatenate([parts[k][1] for k in parts]).astype(np.float32)
            return spaces.Box(lo, hi, dtype=np.float32)
        d = {k: spaces.Box(lo.astype(np.float32), hi.astype(np.float32), dtype=np.float32)
             for k, (lo, hi) in parts.items()}
        if self.image:
            d["image"] = spaces.Box(0, 255, (*self.image_hw, 3), dtype=np.uint8)
        return spaces.Dict(d)

    # ------------------------------------------------------------------------- world
    def _build_world(self) -> None:
        cid = p.connect(p.DIRECT)
        if cid < 0:
            raise RuntimeError("pybullet.connect(DIRECT) failed")
        self._client = cid
        kw = {"physicsClientId": cid}
        p.setTimeStep(1.0 / self.physics_hz, **kw)
        p.setGravity(0, 0, 0, **kw)
        p.setPhysicsEngineParameter(numSolverIterations=10, deterministicOverlappingPairs=1, **kw)
        vis = self.image

        def static_box(cx, cy, cz, hx, hy, hz, yaw, rgba, collide=True):
            col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[hx, hy, hz], **kw) if collide else -1
            v = p.createVisualShape(p.GEOM_BOX, halfExtents=[hx, hy, hz], rgbaColor=rgba, **kw) if vis else -1
            return p.createMultiBody(0, col, v, [cx, cy, cz], p.getQuaternionFromEuler([0, 0, yaw]), **kw)

        # walls: inner faces on |x| + |y| = ARENA_HALF_DIAG
        t = geo.WALL_THICKNESS / 2
        r = geo.ARENA_HALF_DIAG / math.sqrt(2) + t
        for k in range(4):
            a = math.pi / 4 + k * math.pi / 2
            static_box(r * math.cos(a), r * math.sin(a), geo.WALL_HEIGHT / 2, t, 1.6,
                       geo.WALL_HEIGHT / 2, a, [0.55, 0.4, 0.25, 1])
        for cx, cy, hx, hy in geo.BOXES:
            static_box(cx, cy, geo.BOX_HEIGHT / 2, hx, hy, geo.BOX_HEIGHT / 2, 0.0, [0.3, 0.3, 0.32, 1])
        if vis:
            static_box(0, 0, -0.005, 2.5, 2.5, 0.005, 0.0, [0.78, 0.76, 0.7, 1], collide=False)
            for (cx, cy), (nx, ny) in zip(geo.FIELD_POS, geo.FIELD_NORMAL):
                static_box(cx, cy, 0.1, 0.002, 0.04, 0.04, math.atan2(ny, nx), [0.95, 0.95, 0.95, 1],
                           collide=False)
                static_box(cx + 0.001 * nx, cy + 0.001 * ny, 0.1, 0.002, 0.015, 0.015,
                           math.atan2(ny, nx), [0.05, 0.05, 0.05, 1], collide=False)

        fx, fy = geo.FOOTPRINT_HALF
        body_h = 0.075
        col = p.createCollisionShapeArray(
            [p.GEOM_BOX, p.GEOM_CYLINDER], halfExtents=[[fx, fy, body_h], [0, 0, 0]],
            radii=[0, geo.HOUSING_R], lengths=[0, 0.04],
            collisionFramePositions=[[geo.FOOTPRINT_CX, 0, 0.01 + body_h], [geo.HOUSING_X, 0, 0.18]], **kw)
        self._robots = []
        for k, start in enumerate((geo.RED_START, geo.BLUE_START)):
            if vis:
                colour = [0.85, 0.1, 0.1, 1] if k == 0 else [0.1, 0.25, 0.9, 1]
                mk = [[m[1], m[2], 0.1] for m in geo.ROBOT_MARKERS]
                quats = [p.getQuaternionFromEuler([0, 0, m[3]]) for m in geo.ROBOT_MARKERS]
                v = p.createVisualShapeArray(
                    [p.GEOM_BOX, p.GEOM_CYLINDER] + [p.GEOM_BOX] * 3,
                    halfExtents=[[fx, fy, body_h], [0, 0, 0]] + [[0.002, 0.03, 0.03]] * 3,
                    radii=[0, geo.HOUSING_R, 0, 0, 0], lengths=[0, 0.04, 0, 0, 0],
                    rgbaColors=[colour, [0.15, 0.15, 0.15, 1]] + [[0.95, 0.95, 0.95, 1]] * 3,
                    visualFramePositions=[[geo.FOOTPRINT_CX, 0, 0.01 + body_h], [geo.HOUSING_X, 0, 0.18]] + mk,
                    visualFrameOrientations=[[0, 0, 0, 1], [0, 0, 0, 1]] + quats, **kw)
            else:
                v = -1
            body = p.createMultiBody(
                baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
                basePosition=[0, 0, 0], linkMasses=[0.05, 0.05, geo.ROBOT_MASS],
                linkCollisionShapeIndices=[-1, -1, col], linkVisualShapeIndices=[-1, -1, v],
                linkPositions=[[0, 0, 0]] * 3, linkOrientations=[[0, 0, 0, 1]] * 3,
                linkInertialFramePositions=[[0, 0, 0]] * 3,
                linkInertialFrameOrientations=[[0, 0, 0, 1]] * 3, linkParentIndices=[0, 1, 2],
                linkJointTypes=[p.JOINT_PRISMATIC, p.JOINT_PRISMATIC, p.JOINT_REVOLUTE],
                linkJointAxis=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], **kw)
            for j in range(3):
                p.changeDynamics(body, j, linearDamping=0, angularDamping=0, jointDamping=0,
                                 lateralFriction=0.3, **kw)
                p.resetJointState(body, j, start[j], 0.0, **kw)
            self._robots.append(body)
        self._forces = (50.0, 50.0, 5.0)  # N, N, N m: enough to reach full speed in one step
        self._state_id = p.saveState(**kw)
        if self.image:
            h, w = self.image_hw
            vfov = 2 * math.atan(math.tan(geo.CAMERA_HFOV / 2) * h / w)
            self._proj = p.computeProjectionMatrixFOV(math.degrees(vfov), w / h, 0.01, 6.0, **kw)
        self._poses = np.array([geo.RED_START, geo.BLUE_START], dtype=np.float64)
        self._reader = geo.MarkerReader(self.read_range, self._cos_read)
        self._cmd = [(0.0, 0.0), (0.0, 0.0)]
        self._vel = [(0.0, 0.0), (0.0, 0.0)]
        self._pose_err = np.zeros((2, 3))
        self._pose_ref: list[np.ndarray | None] = [None, None]

    # ------------------------------------------------------------------------- physics helpers
    def _read_poses(self) -> None:
        cid = self._client
        for k, body in enumerate(self._robots):
            js = p.getJointStates(body, (0, 1, 2), physicsClientId=cid)
            self._poses[k, 0] = js[0][0]
            self._poses[k, 1] = js[1][0]
            self._poses[k, 2] = js[2][0]

    def _apply_cmd(self, k: int, v: float, w: float, yaw: float) -> None:
        """Velocity targets for robot k over the next physics step (heading at mid-step)."""
        yaw += 0.5 * w / self.physics_hz
        p.setJointMotorControlArray(self._robots[k], (0, 1, 2), p.VELOCITY_CONTROL,
                                    targetVelocities=(v * math.cos(yaw), v * math.sin(yaw), w),
                                    forces=self._forces, physicsClientId=self._client)

    def set_poses(self, red: Sequence[float], blue: Sequence[float]):
        """Teleport both robots (world frame (x, y, yaw), zero velocity); returns the agent's new
        observation (lidar re-drawn). For tests and debugging."""
        for body, pose in zip(self._robots, (red, blue)):
            for j in range(3):
                p.resetJointState(body, j, float(pose[j]), 0.0, physicsClientId=self._client)
        self._read_poses()
        self._agent_lidar = self._scan(self.agent_side)
        return self._obs(self.agent_side, self._agent_lidar)

    @property
    def poses(self) -> np.ndarray:
        """float64[2, 3]: world poses (x, y, yaw) of red and blue."""
        return self._poses.copy()

    # ------------------------------------------------------------------------- sensors
    def _scan(self, k: int) -> np.ndarray:
        """Noisy float32[360] lidar of robot k (0 red, 1 blue), not yet clipped."""
        return self._scans((k,))[0]

    def _scans(self, ks: Sequence[int]) -> list[np.ndarray]:
        """Noisy lidar of the robots ``ks`` in one vectorised call (noise drawn in that order),
        not yet clipped: :meth:`_obs_lidar` applies the sensor's range convention."""
        ks = list(ks)
        poses = self._poses[ks]
        circles = np.array([geo.housing_circle(*self._poses[1 - k]) for k in ks])
        r = self._lidar.scan_many(poses, circles)
        if self.lidar_noise > 0:
            r += self.np_random.normal(0.0, self.lidar_noise, r.shape).astype(np.float32)
        return list(r)

    def _obs_lidar(self, raw: np.ndarray) -> np.ndarray:
        """The observed scan: readings outside the sensor's range clipped into it (default), or
        shown as the invalid value (0 / inf), as are beams that drop out."""
        if self._lidar_fill is None:
            return np.clip(raw, geo.LIDAR_MIN, geo.LIDAR_MAX)
        bad = (raw < geo.LIDAR_MIN) | (raw > geo.LIDAR_MAX)
        if self.lidar_dropout > 0:
            bad |= self.np_random.random(raw.shape) < self.lidar_dropout
        return np.where(bad, np.float32(self._lidar_fill), raw).astype(np.float32)

    def _observed_pose(self, k: int) -> np.ndarray:
        """World pose of robot k as its localisation reports it: exact, or with an AMCL-like
        offset that is drawn anew only once the robot has moved or turned enough."""
        pose = self._poses[k]
        if self.pose_noise == 0 and self.pose_noise_yaw == 0:
            return pose
        ref = self._pose_ref[k]
        if ref is None or (math.hypot(pose[0] - ref[0], pose[1] - ref[1]) >= self.pose_update[0]
                           or abs(math.remainder(pose[2] - ref[2], 2 * math.pi)) >= self.pose_update[1]):
            sig = (self.pose_noise, self.pose_noise, self.pose_noise_yaw)
            self._pose_err[k] = self.np_random.normal(0.0, 1.0, 3) * sig
            self._pose_ref[k] = pose.copy()
        noisy = pose + self._pose_err[k]
        # the estimate stays inside the map, like AMCL's particles
        h = geo.ARENA_HALF_DIAG
        noisy[:2] = np.clip(noisy[:2], -h, h)
        return noisy

    def _camera(self, k: int) -> np.ndarray:
        x, y, yaw = self._poses[k]
        c, s = math.cos(yaw), math.sin(yaw)
        ex, ey = x + geo.CAMERA_X * c, y + geo.CAMERA_X * s
        view = p.computeViewMatrix([ex, ey, geo.CAMERA_Z], [ex + c, ey + s, geo.CAMERA_Z], [0, 0, 1],
                                   physicsClientId=self._client)
        h, w = self.image_hw
        img = p.getCameraImage(w, h, view, self._proj, renderer=p.ER_TINY_RENDERER,
                               flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self._client)[2]
        return np.asarray(img, dtype=np.uint8).reshape(h, w, 4)[:, :, :3].copy()

    def _reads_both(self) -> tuple[list[int], list[int]]:
        """Target indices red and blue read now (each: 12 field markers + the enemy's 3)."""
        red, blue = self._poses.tolist()
        return (self._reader.reads(red, blue, geo.BLUE_MARKERS),
                self._reader.reads(blue, red, geo.RED_MARKERS))

    def _serve_reads(self, red: list[int], blue: list[int]) -> list[dict]:
        """One judge tick. The real judge serves requests one at a time, in whatever order they
        arrive; when both robots read in the same tick, a fair coin (from ``np_random``, drawn
        only then) says whether the agent's requests come first, so neither side is favoured
        and a mirrored episode with the same seed mirrors this too."""
        order = "rb"
        if red and blue:
            agent_first = bool(self.np_random.random() < 0.5)
            order = "rb" if agent_first == (self.agent_side == 0) else "br"
        return self.judge.read(red, blue, order)

    def _obs(self, k: int, lidar: np.ndarray, image: bool | None = None):
        """Robot k's observation from its raw (unclipped) scan ``lidar``."""
        x, y, yaw = geo.to_frame(*self._observed_pose(k), k)
        jt = self.judge
        mine, theirs = (jt.scores[0], jt.scores[1]) if k == 0 else (jt.scores[1], jt.scores[0])
        mask = _MASK_LUT[k][jt.owners[_VIEW_INDEX[k]]]
        obs = {
            "lidar": self._obs_lidar(lidar),
            "pose": np.array([x, y, math.cos(yaw), math.sin(yaw)], np.float32),
            "mask": mask,
            "game": np.array([jt.time / jt.match_time, float(jt.sudden_death),
                              mine / _SCORE_NORM, theirs / _SCORE_NORM], np.float32),
        }
        if self.privileged:
            ex, ey, eyaw = geo.to_frame(*self._poses[1 - k], k)
            obs["enemy_pose"] = np.array([ex, ey, math.cos(eyaw), math.sin(eyaw)], np.float32)
        if self.enemy_detector:
            obs["enemy_seen"] = geo.detect_circle(lidar, self._poses[k],
                                                  geo.housing_circle(*self._poses[1 - k]))
            if k == self.agent_side:
                self._agent_seen = obs["enemy_seen"]
        if self.flatten_obs:
            return np.concatenate([obs[key] for key in self._flat_keys])
        if self.image if image is None else image:
            obs["image"] = self._camera(k)
        return obs

    # ------------------------------------------------------------------------- gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """options: ``side`` ("red"/"blue"/"random") and ``opponent`` (a name) override the
        env's choice for this episode."""
        super().reset(seed=seed)
        options = options or {}
        rng = self.np_random
        side = options.get("side", self.side_option)
        if side == "random":
            side = SIDES[int(rng.integers(2))]
        self.agent_side = SIDES.index(side)
        name = options.get("opponent")
        if name is None:
            name = self._opp_names[int(rng.choice(len(self._opp_names), p=self._opp_probs))]
        if name not in self._opps:
            self._opps[name] = make_opponent(name, self.opponent_policy, self.control_hz)
        self.opponent_name = name
        self.opponent = self._opps[name]
        self.opponent.reset(rng)
        self._opp_period = max(1, int(round(self.physics_hz / self.opponent.hz)))

        p.restoreState(self._state_id, physicsClientId=self._client)
        if self.start_noise > 0:
            for body, start in zip(self._robots, (geo.RED_START, geo.BLUE_START)):
                jit = rng.normal(0.0, self.start_noise, 3) * np.array([1.0, 1.0, 2.0])
                for j in range(3):
                    p.resetJointState(body, j, start[j] + jit[j], 0.0, physicsClientId=self._client)
        self._read_poses()
        self._cmd = [(0.0, 0.0), (0.0, 0.0)]
        self._vel = [(0.0, 0.0), (0.0, 0.0)]
        self._pose_ref = [None, None]
        self._n = 0
        self._steps = 0
        self._opp_lidar_at = -1
        self._opp_lidar = None
        players = ["agent", name] if self.agent_side == 0 else [name, "agent"]
        self.judge.players = tuple(players)
        self.judge.reset()
        self._agent_lidar = self._scan(self.agent_side)
        obs = self._obs(self.agent_side, self._agent_lidar)
        return obs, self._info([], {})

    def _to_cmd(self, action) -> tuple[float, float]:
        if self._actions is not None:
            v, w = self._actions[int(np.asarray(action).reshape(-1)[0]) if np.ndim(action) else int(action)]
        else:
            a = np.asarray(action, dtype=np.float64).reshape(-1)
            v, w = a[0], a[1]
        return _clip(v, geo.MAX_V), _clip(w, geo.MAX_W)

    def _opponent_cmd(self) -> tuple[float, float]:
        k = 1 - self.agent_side
        opp = self.opponent
        x, y, yaw = geo.to_frame(*self._poses[k], k)
        lidar = None
        if opp.needs_lidar or opp.needs_obs:
            if self._opp_lidar_at == self._n:
                lidar = self._opp_lidar
            else:
                lidar = self._scan(k)
        obs = self._obs(k, lidar) if opp.needs_obs else None
        if lidar is not None:
            lidar = np.clip(lidar, geo.LIDAR_MIN, geo.LIDAR_MAX)
        view = OpponentView(x, y, yaw, self.judge.time, lidar, obs)
        if opp.needs_enemy:
            view.enemy = geo.to_frame(*self._poses[1 - k], k)
            # the agent's L, R, B markers (RE_* for red, BL_* for blue) that this opponent has read
            first = geo.N_FIELD + 3 * (1 - k)
            view.taken = tuple(bool(o == k + 1) for o in self.judge.owners[first:first + 3])
        out = opp.act(view)
        if opp.needs_obs:
            return self._to_cmd(out)
        v, w = out
        return _clip(v, geo.MAX_V), _clip(w, geo.MAX_W)

    def step(self, action):
        a, o = self.agent_side, 1 - self.agent_side
        self._cmd[a] = self._to_cmd(action)
        jt = self.judge
        before = jt.owners.copy()
        scores_before = jt.scores
        captures: list[dict] = []
        cid = self._client
        dt = 1.0 / self.physics_hz
        yaw = [self._poses[0, 2], self._poses[1, 2]]  # predicted yaw between pose reads
        sent = [None, None]
        stale = False
        for _ in range(self._sub):
            if self._n % self._opp_period == 0:
                if stale:
                    self._read_poses()
                    yaw = [self._poses[0, 2], self._poses[1, 2]]
                    stale = False
                self._cmd[o] = self._opponent_cmd()
            for k in (0, 1):
                v, w = self._cmd[k] if self.accel_limit is None else self._ramp(k, dt)
                if w != 0.0 or sent[k] != (v, w):
                    self._apply_cmd(k, v, w, yaw[k])
                    sent[k] = (v, w)
                yaw[k] += w * dt
            p.stepSimulation(physicsClientId=cid)
            self._n += 1
            stale = True
            if self._n % self._cap_every == 0:
                self._read_poses()
                yaw = [self._poses[0, 2], self._poses[1, 2]]
                stale = False
                jt.time = self._n * dt
                captures += self._serve_reads(*self._reads_both())
            jt.set_time(self._n * dt)
            if jt.done:
                break
        if stale:
            self._read_poses()
        self._steps += 1
        terminated = jt.done
        truncated = bool(self.max_steps is not None and self._steps >= self.max_steps and not terminated)
        opp = self.opponent
        if (opp.needs_lidar or opp.needs_obs) and not jt.done and self._n % self._opp_period == 0:
            # the opponent decides at the start of the next step, from these very poses
            self._agent_lidar, self._opp_lidar = self._scans((a, o))
            self._opp_lidar_at = self._n
        else:
            self._agent_lidar = self._scan(a)
        comps = self._reward(before, scores_before, terminated)
        obs = self._obs(a, self._agent_lidar)
        if self.face_penalty:
            comps["facing"] = self.face_penalty if self._off_facing(self._agent_seen) else 0.0
        reward = float(sum(comps.values()))
        info = self._info(captures, comps)
        if terminated or truncated:
            info["outcome"], info["my_score"], info["enemy_score"] = match_outcome(info)
            info["my_robot_points"], info["enemy_robot_points"] = robot_marker_points(info)
        return obs, reward, terminated, truncated, info

    @property
    def action_table(self) -> tuple[tuple[float, float], ...] | None:
        """The discrete action set's ``(v m/s, w rad/s)`` rows, None for "continuous"."""
        return {"users": USERS_ACTIONS, "rich": RICH_ACTIONS}.get(self.action_set)

    def guard_rule(self) -> GuardRule:
        """The guard's rule for this env: ``face_radius``, ``face_angle`` and the action set's
        fastest turns on the spot (the rule the ``facing`` term pays on, ``actor.guard_share``
        acts on and ``learner.guard_imitation`` teaches). ValueError for the continuous action
        set."""
        if self.action_table is None:
            raise ValueError("the guard needs a discrete action set with turns on the spot (users or rich)")
        return self._guard

    def guard_action(self, seen: np.ndarray) -> int:
        """The guard's action on the detector's reading ``seen`` (float[3]: seen, x forward, y
        left; m): the fastest turn on the spot towards the other robot where it is nearer than
        ``face_radius`` and more than ``face_angle`` off the heading, else -1
        (:meth:`guard_rule`). ValueError for the continuous action set."""
        return int(self.guard_rule().actions(seen)[0])

    def _off_facing(self, seen: np.ndarray) -> bool:
        """Whether the detector's ``seen`` (seen, x forward, y left; m) puts the other robot
        nearer than ``face_radius`` and more than ``face_angle`` off the heading (the rule of
        ``zenrl export --guard``, which acts on the same reading)."""
        return bool(self._guard.off_facing(seen)[0])

    def _ramp(self, k: int, dt: float) -> tuple[float, float]:
        """Robot k's speeds for the next physics step: towards the command, changing by at most
        ``accel_limit * dt``."""
        (v0, w0), (v1, w1) = self._vel[k], self._cmd[k]
        av, aw = self.accel_limit
        v = v0 + _clip(v1 - v0, av * dt)
        w = w0 + _clip(w1 - w0, aw * dt)
        self._vel[k] = (v, w)
        return v, w

    def _reward(self, before: np.ndarray, scores_before, terminated: bool) -> dict[str, float]:
        a = self.agent_side
        jt = self.judge
        me = RED if a == 0 else BLUE
        if self.reward_mode == "users":
            if np.array_equal(before, jt.owners):
                gain = loss = 0.0
            else:
                gain, loss = self._users_marker_reward(before, jt.owners, me, a, self._marker_weights)
            x, y, _ = self._poses[a]
            wall = (geo.ARENA_HALF_DIAG - abs(x) - abs(y)) / math.sqrt(2)
            return {"marker_gain": gain, "robot_loss": loss,
                    "wall": self.wall_penalty if wall < self.wall_dist else 0.0,
                    "far": self.far_penalty if math.hypot(x, y) > self.far_dist else 0.0}
        sign = 1 if a == 0 else -1
        outcome = 0.0
        if terminated and jt.winner != "draw":
            outcome = 1.0 if jt.winner == "rb"[a] else -1.0
        if self.reward_mode == "zero_sum":
            diff_now = sign * (jt.scores[0] - jt.scores[1])
            diff_before = sign * (scores_before[0] - scores_before[1])
            return {"score_diff": float(diff_now - diff_before), "win_bonus": self.win_bonus * outcome}
        return {"outcome": outcome}

    @staticmethod
    def _users_marker_reward(before: np.ndarray, owners: np.ndarray, me: int, a: int,
                             weights: np.ndarray) -> tuple[float, float]:
        """The users' marker terms: marker value +w mine, 0 neutral, -w enemy's (w = 1, or the
        marker's points with ``marker_values="points"``); gain = sum of the positive changes
        over field + enemy robot markers (a retake is +2w), loss = sum of the negative changes
        over my robot's markers."""
        def value(o):
            return np.where(o == me, 1.0, np.where(o == NEUTRAL, 0.0, -1.0))

        d = (value(owners) - value(before)) * weights
        own = geo.RED_MARKERS if a == 0 else geo.BLUE_MARKERS
        sel = np.ones(geo.N_TARGETS, bool)
        sel[own] = False
        return float(np.maximum(d[sel], 0).sum()), float(np.minimum(d[own], 0).sum())

    def _info(self, captures: list[dict], comps: dict[str, float]) -> dict:
        return {"war_state": self.judge.war_state(), "captures": captures,
                "winner": self.judge.winner, "reward_components": comps,
                "side": SIDES[self.agent_side], "opponent": self.opponent_name}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = TopDownRenderer(self.render_size)
        jt = self.judge
        return self._renderer.draw(self._poses, jt.owners, jt.scores, jt.time, jt.state, jt.sudden_death)

    def close(self):
        if self._client >= 0:
            try:
                p.disconnect(physicsClientId=self._client)
            except p.error:  # already gone
                log.debug("pybullet client %d already disconnected", self._client)
            self._client = -1
        super().close()
