"""The Burger War Gymnasium envs: API, determinism, symmetry, containment, rendering."""

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import zenrl.common.envs  # noqa: F401  (registers the ids)
from zenrl.games.burgerwar import geometry as geo
from zenrl.games.burgerwar.env import BurgerWarEnv


@pytest.fixture
def make(make_bw):
    return make_bw


def test_registered_ids_and_spaces():
    for env_id, image in (("zenrl/BurgerWar-v0", False), ("zenrl/BurgerWarImage-v0", True)):
        env = gym.make(env_id, image_size=32, opponents="idle")
        try:
            obs, info = env.reset(seed=1)
            assert env.observation_space.contains(obs)
            assert ("image" in obs) == image
            if image:
                assert obs["image"].shape == (32, 32, 3) and obs["image"].dtype == np.uint8
            assert obs["lidar"].shape == (360,) and obs["mask"].shape == (18,)
            assert obs["pose"].shape == (4,) and obs["game"].shape == (4,)
            assert env.spec.max_episode_steps is None
            obs, r, term, trunc, info = env.step(0)
            assert env.observation_space.contains(obs)
            assert set(info) >= {"war_state", "captures", "winner", "reward_components"}
        finally:
            env.close()


@pytest.mark.parametrize("kw", [dict(), dict(image=True, image_size=16), dict(flatten_obs=True),
                                dict(action_set="continuous", privileged=True)])
def test_check_env(kw):
    env = BurgerWarEnv(opponents="teriyaki", render_mode="rgb_array", render_size=64, **kw)
    try:
        check_env(env, skip_render_check=False)
    finally:
        env.close()


def test_initial_observation(make):
    env = make(opponents="idle", lidar_noise=0.0)
    obs, info = env.reset(seed=0)
    np.testing.assert_allclose(obs["pose"], [0.0, -1.3, 0.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(obs["mask"], np.ones(18))  # all neutral
    np.testing.assert_array_equal(obs["game"], np.zeros(4))
    # forward beam sees the centre box: 1.3 - 0.175 + 0.032 from the sensor
    assert obs["lidar"][0] == pytest.approx(1.3 - 0.175 + 0.032, abs=1e-5)
    assert info["war_state"]["state"] == "running" and info["winner"] is None


def _run(env, seed, n, action_seed=0):
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(action_seed)
    out = [obs]
    for _ in range(n):
        obs, r, term, trunc, info = env.step(int(rng.integers(5)))
        out.append((obs, r, term, info["war_state"], info["captures"]))
        if term or trunc:
            break
    return out


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


def test_same_seed_same_episode(make):
    kw = dict(opponents={"teriyaki": 1, "waypoint": 1, "random": 1}, side="random")
    a, b = make(**kw), make(**kw)
    ra = _run(a, 7, 250)
    _run(b, 3, 100)  # b runs another episode first: reset must restore everything
    rb = _run(b, 7, 250)
    assert _same(ra, rb)
    assert a.opponent_name == b.opponent_name and a.agent_side == b.agent_side


def test_different_seeds_differ(make):
    a = make(opponents="random")
    r1, r2 = _run(a, 1, 50), _run(a, 2, 50)
    assert not _same(r1, r2)


def _mirror(pose):
    return (-pose[0], -pose[1], pose[2] + math.pi)


def test_red_and_blue_observations_mirror(make):
    red_env = make(side="red", opponents="idle", lidar_noise=0.0, privileged=True)
    blue_env = make(side="blue", opponents="idle", lidar_noise=0.0, privileged=True)
    o_r, _ = red_env.reset(seed=0)
    o_b, _ = blue_env.reset(seed=0)
    for k in o_r:
        np.testing.assert_allclose(o_r[k], o_b[k], atol=1e-5)
    me, other = (0.4, -0.8, 0.7), (-0.3, 0.5, -2.2)
    o_r = red_env.set_poses(me, other)
    o_b = blue_env.set_poses(_mirror(other), _mirror(me))
    # ownership: red agent owns Tomato_N and blue's back marker; in the mirrored match the blue
    # agent owns the mirrored field marker and red's back marker
    names = geo.TARGET_NAMES
    jr, jb = red_env.judge, blue_env.judge
    jr.read(red_reads=[names.index("Tomato_N"), names.index("BL_B")],
            blue_reads=[names.index("FriedShrimp_E")])
    jb.read(blue_reads=[int(geo.FIELD_MIRROR[names.index("Tomato_N")]), names.index("RE_B")],
            red_reads=[int(geo.FIELD_MIRROR[names.index("FriedShrimp_E")])])
    o_r = red_env._obs(0, o_r["lidar"])
    o_b = blue_env._obs(1, o_b["lidar"])
    for k in o_r:
        np.testing.assert_allclose(o_r[k], o_b[k], atol=1e-5, err_msg=k)
    assert o_r["mask"][names.index("Tomato_N")] == 0  # mine
    assert o_r["mask"][12 + 5] == 0 and o_r["mask"][12 + 2] == 1  # enemy back taken, mine neutral
    assert o_r["game"][2] == pytest.approx(0.6) and o_r["game"][3] == pytest.approx(0.1)


def test_red_and_blue_mirror_dynamically(make):
    """The same actions from mirrored starts give (nearly) the same own-frame episodes."""
    red_env = make(side="red", opponents="cheese", lidar_noise=0.0)
    blue_env = make(side="blue", opponents="cheese", lidar_noise=0.0)
    o_r, _ = red_env.reset(seed=0)
    o_b, _ = blue_env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(150):
        a = int(rng.integers(5))
        o_r, r_r, *_ = red_env.step(a)
        o_b, r_b, *_ = blue_env.step(a)
        np.testing.assert_allclose(o_r["pose"], o_b["pose"], atol=1e-4)
        np.testing.assert_allclose(o_r["lidar"], o_b["lidar"], atol=1e-3)
        np.testing.assert_array_equal(o_r["mask"], o_b["mask"])
        assert r_r == r_b


def _penetration(poses: np.ndarray) -> float:
    """Deepest penetration (m) of footprints (N poses) into walls/boxes, or of box corners into
    footprints."""
    worst = 0.0
    boxes = np.concatenate([geo.box_corners(i) for i in range(len(geo.BOXES))])  # (20, 2)
    for pose in poses:
        c = geo.footprint_corners(*pose)
        worst = max(worst, -geo.point_static_clearance(c[:, 0], c[:, 1]).min())
        # box corners inside the footprint (in the robot frame)
        x, y, yaw = pose
        rel = boxes - (x, y)
        lx = rel[:, 0] * math.cos(yaw) + rel[:, 1] * math.sin(yaw) - geo.FOOTPRINT_CX
        ly = -rel[:, 0] * math.sin(yaw) + rel[:, 1] * math.cos(yaw)
        depth = np.minimum(geo.FOOTPRINT_HALF[0] - np.abs(lx), geo.FOOTPRINT_HALF[1] - np.abs(ly))
        worst = max(worst, depth.max())
    return worst


def test_robots_stay_in_field_and_out_of_boxes(make):
    """A long random drive of both robots at full speed: contact penetration stays below 1 cm."""
    env = make(opponents="random", action_set="continuous", lidar_noise=0.0)
    rng = np.random.default_rng(3)
    poses, overlaps, steps = [], 0, 0
    for ep in range(2):
        env.reset(seed=100 + ep)
        for t in range(1200):
            if t % 10 == 0:
                a = rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)
            _, _, term, trunc, _ = env.step(a)
            steps += 1
            poses.append(env.poses)
            if t % 5 == 0:
                rf, bf = geo.footprint_corners(*env.poses[0]), geo.footprint_corners(*env.poses[1])
                overlaps += geo.polygons_overlap(rf, bf, 0.01)
            if term or trunc:
                break
    poses = np.concatenate(poses)
    assert steps > 1000
    assert _penetration(poses) < 0.01
    assert overlaps == 0
    # they did drive around (not stuck at the start)
    assert np.ptp(poses[:, 0]) > 0.5 and np.ptp(poses[:, 1]) > 0.5


def test_render_shows_robots(make):
    env = make(opponents="idle", render_mode="rgb_array", render_size=200)
    env.reset(seed=0)
    red, blue = (0.5, -0.9, 0.3), (-0.7, 0.4, 2.0)
    env.set_poses(red, blue)
    frame = env.render()
    assert frame.shape == (200, 200, 3) and frame.dtype == np.uint8
    r = env._renderer
    for pose, colour in ((red, (220, 30, 30)), (blue, (30, 70, 230))):
        # a point of the footprint behind the base origin (the front carries the heading dot)
        x = pose[0] - 0.06 * math.cos(pose[2])
        y = pose[1] - 0.06 * math.sin(pose[2])
        row, col = r.to_px(x, y)
        assert tuple(frame[row, col]) == colour
    # moving the robot moves its pixels
    env.set_poses((0.9, 0.3, 0.0), blue)
    frame2 = env.render()
    row, col = r.to_px(red[0] - 0.06 * math.cos(red[2]), red[1] - 0.06 * math.sin(red[2]))
    assert tuple(frame2[row, col]) != (220, 30, 30)
    assert not np.array_equal(frame, frame2)


def test_render_text_font():
    from zenrl.games.burgerwar.render import FONT, draw_text

    img = np.zeros((10, 40, 3), np.uint8)
    draw_text(img, "R 10", 1, 1)
    assert img.any() and set("0123456789:.RB") <= set(FONT)


def test_flatten_and_privileged(make):
    env = make(flatten_obs=True, privileged=True, opponents="idle")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (360 + 4 + 18 + 4 + 4,) and obs.dtype == np.float32
    np.testing.assert_allclose(obs[-4:], [0.0, 1.3, 0.0, -1.0], atol=1e-6)  # enemy in front
    with pytest.raises(ValueError):
        BurgerWarEnv(flatten_obs=True, image=True)


@pytest.mark.parametrize("action_set,n", [("users", 5), ("rich", 15)])
def test_discrete_action_sets(make, action_set, n):
    env = make(action_set=action_set, opponents="idle", lidar_noise=0.0)
    assert env.action_space.n == n
    env.reset(seed=0)
    y0 = env.poses[0, 1]
    for _ in range(10):
        env.step(0)  # full speed ahead in both sets
    assert env.poses[0, 1] - y0 == pytest.approx(0.2 if action_set == "users" else 0.22, abs=0.01)


def test_continuous_actions_clipped(make):
    env = make(action_set="continuous", opponents="idle")
    env.reset(seed=0)
    env.step(np.array([1.0, 0.0], np.float32))
    assert env.poses[0, 1] - (-1.3) == pytest.approx(0.022, abs=2e-3)
    env.step(np.array([0.0, 10.0], np.float32))
    assert env.poses[0, 2] - math.pi / 2 == pytest.approx(0.284, abs=5e-3)


def test_control_hz_one_matches_users_agent(make):
    env = make(control_hz=1, opponents="idle")
    env.reset(seed=0)
    obs, *_ = env.step(0)
    assert obs["game"][0] == pytest.approx(1.0 / 180)
    assert obs["pose"][1] == pytest.approx(-1.1, abs=0.01)


def test_rewards(make):
    # users: reading a neutral marker +1
    env = make(opponents="idle", reward="users", lidar_noise=0.0)
    env.reset(seed=0)
    env.set_poses((0.0, -0.75, math.pi / 2), (0.0, 1.3, -math.pi / 2))
    _, r, _, _, info = env.step(2)
    assert info["reward_components"]["marker_gain"] == 1.0
    assert r == pytest.approx(sum(info["reward_components"].values()))
    # users: retaking from the enemy is +2; near the wall -0.5, far from the centre -0.5
    env.judge.owners[geo.TARGET_NAMES.index("FriedShrimp_S")] = 2
    env.set_poses((0.0, -0.75, math.pi / 2), (0.0, 1.3, -math.pi / 2))
    _, r, _, _, info = env.step(2)
    assert info["reward_components"]["marker_gain"] == 2.0
    env.set_poses((0.0, -1.5, math.pi), (0.0, 1.3, -math.pi / 2))
    _, r, _, _, info = env.step(2)
    assert info["reward_components"]["wall"] == -0.5 and info["reward_components"]["far"] == -0.5
    # zero_sum: change in score difference, terminal bonus
    env2 = make(opponents="idle", reward="zero_sum", lidar_noise=0.0, match_time=1.0,
                sudden_death_time=1.0, win_bonus=5.0)
    env2.reset(seed=0)
    env2.set_poses((0.0, -0.75, math.pi / 2), (0.0, 1.3, -math.pi / 2))
    _, r, term, _, info = env2.step(2)
    assert info["reward_components"]["score_diff"] == 1.0 and not term
    total = r
    for _ in range(20):
        _, r, term, _, info = env2.step(2)
        total += r
        if term:
            break
    assert term and info["winner"] == "r" and info["reward_components"]["win_bonus"] == 5.0
    assert total == pytest.approx(6.0)
    # sparse: draw at the end of sudden death
    env3 = make(opponents="idle", reward="sparse", match_time=0.5, sudden_death_time=0.5)
    env3.reset(seed=0)
    for _ in range(20):
        _, r, term, _, info = env3.step(2)
        if term:
            break
    assert term and info["winner"] == "draw" and r == 0.0
    assert info["war_state"]["time"] == pytest.approx(1.0)


def test_policy_opponent_sees_its_own_frame(make):
    seen = []

    def policy(obs):
        seen.append(obs["pose"].copy())
        return 0  # forward

    env = make(opponents="policy", opponent_policy=policy, lidar_noise=0.0)
    env.reset(seed=0)
    for _ in range(5):
        env.step(2)
    np.testing.assert_allclose(seen[0], [0.0, -1.3, 0.0, 1.0], atol=1e-6)
    assert env.poses[1, 1] < 1.3 - 0.07  # blue drove forward (towards -y in the world)


def test_vector_env_batched(make):
    fns = [lambda i=i: BurgerWarEnv(opponents="teriyaki", side="random", flatten_obs=True) for i in range(3)]
    venv = gym.vector.SyncVectorEnv(fns)
    try:
        obs, info = venv.reset(seed=[0, 1, 2])
        assert obs.shape == (3, 386)
        for _ in range(20):
            obs, r, term, trunc, info = venv.step(venv.action_space.sample())
        assert obs.shape == (3, 386) and r.shape == (3,)
    finally:
        venv.close()


def test_reset_options_and_max_steps(make):
    env = make(opponents=["idle", "cheese"], max_steps=3)
    _, info = env.reset(seed=0, options={"side": "blue", "opponent": "cheese"})
    assert info["side"] == "blue" and info["opponent"] == "cheese"
    assert info["war_state"]["players"] == {"r": "cheese", "b": "agent"}
    for i in range(3):
        _, _, term, trunc, _ = env.step(2)
    assert trunc and not term


def test_enemy_detector_hand_geometry():
    """detect_circle against positions worked out by hand on a noise-free scan."""
    lidar = geo.Lidar()
    me = (-0.9, 0.0, 0.0)  # facing +x, left of the central box, in the open
    # the enemy's housing centre 0.5 m ahead of my lidar (which sits LIDAR_X behind my base)
    c = (-0.9 + geo.LIDAR_X + 0.5, 0.0, geo.HOUSING_R)
    ranges = lidar.scan(*me, circle=c)
    assert ranges[0] == pytest.approx(0.5 - geo.HOUSING_R, abs=1e-5)
    seen = geo.detect_circle(ranges, me, c)
    # beam 0 hits the near face at 0.5 - r; centre = reading + r along beam 0
    np.testing.assert_allclose(seen, [1.0, geo.LIDAR_X + 0.5, 0.0], atol=1e-5)
    # the same distance to my left: facing -y, world +x is my left; my lidar is at
    # (-0.9, +0.032), so (x forward, y left) = (LIDAR_X, 0.5)
    me_left = (-0.9, 0.0, -math.pi / 2)
    c_left = (-0.9 + 0.5, -geo.LIDAR_X, geo.HOUSING_R)
    ranges = lidar.scan(*me_left, circle=c_left)
    np.testing.assert_allclose(geo.detect_circle(ranges, me_left, c_left), [1.0, geo.LIDAR_X, 0.5],
                               atol=1e-5)
    me = (0.0, -1.0, 0.0)
    c = (geo.LIDAR_X + 0.8, -1.0, geo.HOUSING_R)
    # behind the central box (0.35 m square at the origin): the scan reads the box, not it
    me_box = (0.0, -1.0, math.pi / 2)
    c_box = (0.0, 1.0, geo.HOUSING_R)
    ranges = lidar.scan(*me_box, circle=c_box)
    assert ranges[0] < 1.0  # the box's face
    np.testing.assert_array_equal(geo.detect_circle(ranges, me_box, c_box), [0.0, 0.0, 0.0])
    # beyond the sensor's 3.5 m: not seen even with a clear line (a scan without walls)
    far = (geo.LIDAR_X + 3.6, -1.0, geo.HOUSING_R)
    fake = np.full(360, np.inf)
    fake[0] = 3.6 - geo.HOUSING_R
    np.testing.assert_array_equal(geo.detect_circle(fake, me, far), [0.0, 0.0, 0.0])
    # a reading that disagrees with the circle's range (something in between) is not it
    near = np.full(360, np.inf)
    near[0] = 0.8 - geo.HOUSING_R - 0.2
    np.testing.assert_array_equal(geo.detect_circle(near, me, c), [0.0, 0.0, 0.0])


def test_enemy_detector_obs_both_sides(make):
    """obs["enemy_seen"] in the env: the robot's own frame, both sides, flattened last."""
    for side, k in (("red", 0), ("blue", 1)):
        env = make(side=side, opponents="idle", lidar_noise=0.0, enemy_detector=True)
        env.reset(seed=0)
        me = np.array([-0.9, 0.0, 0.0])
        enemy = np.array([-0.4, 0.1, 0.0])
        red, blue = (me, enemy) if k == 0 else (enemy, me)
        obs = env.set_poses(red, blue)
        cx, cy, _ = geo.housing_circle(*enemy)
        # the enemy's housing centre relative to my base, my yaw 0: world dx, dy
        np.testing.assert_allclose(obs["enemy_seen"], [1.0, cx - me[0], cy - me[1]], atol=0.02)
        assert env.observation_space.contains(obs)
    flat = make(opponents="idle", lidar_noise=0.0, enemy_detector=True, privileged=True,
                flatten_obs=True)
    obs, _ = flat.reset(seed=0)
    assert obs.shape == (360 + 4 + 18 + 4 + 4 + 3,)
    np.testing.assert_array_equal(obs[-3:], [0.0, 0.0, 0.0])  # the central box between them


def test_face_penalty_paid_on_what_the_detector_sees(make):
    """The ``facing`` term: paid when the seen robot is near and off the heading, not when it is
    ahead, beyond the radius, or absent (both sides; worked out from the poses by hand)."""
    stop = 2  # users action set: (v, w) = (0, 0)
    for side, k in (("red", 0), ("blue", 1)):
        env = make(side=side, opponents="idle", lidar_noise=0.0, enemy_detector=True, reward="zero_sum",
                   face_penalty=-0.25)
        env.reset(seed=0)

        def step(me, enemy):
            env.set_poses(*((me, enemy) if k == 0 else (enemy, me)))
            _, r, _, _, info = env.step(stop)
            return r, info["reward_components"]

        # 0.5 m straight ahead (bearing ~11 deg to the housing's centre): facing it
        r, c = step((-0.9, 0.0, 0.0), (-0.4, 0.1, 0.0))
        assert c["facing"] == 0.0 and r == c["score_diff"] + c["win_bonus"]
        # the same spot with my heading turned 90 degrees left: it is on my right, 0.5 m away
        r, c = step((-0.9, 0.0, math.pi / 2), (-0.4, 0.1, 0.0))
        assert c["facing"] == -0.25 and r == pytest.approx(-0.25 + c["score_diff"] + c["win_bonus"])
        # 0.84 m away, 45 degrees to my right: inside the default 1.2 m, outside a 0.8 m radius
        assert step((-0.9, 0.0, math.pi / 2), (-0.3, 0.6, 0.0))[1]["facing"] == -0.25
        env = make(side=side, opponents="idle", lidar_noise=0.0, enemy_detector=True, reward="zero_sum",
                   face_penalty=-0.25, face_radius=0.8)
        env.reset(seed=0)
        assert step((-0.9, 0.0, math.pi / 2), (-0.3, 0.6, 0.0))[1]["facing"] == 0.0
    env = make(opponents="idle", enemy_detector=True, reward="zero_sum")
    env.reset(seed=0)
    assert "facing" not in env.step(stop)[4]["reward_components"]  # off by default
    with pytest.raises(ValueError, match="enemy_detector"):
        make(face_penalty=-0.1)
    with pytest.raises(ValueError, match="face_penalty"):
        make(enemy_detector=True, face_penalty=0.5)
