"""The match env's guard as a demonstrator (``actor.guard_share``): the env's ``guard_action``
on the detector's reading (worked out by hand), the guard turning a robot until it faces the
other one, and :class:`~zenrl.actor.policies.Demonstrated` replacing the policy's actions where
the rule acts, at the configured share, with the actions taken returned."""

import math

import numpy as np
import pytest

from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.policies import Demonstrated
from zenrl.actor.service import guard_rule
from zenrl.common.config import EnvConfig
from zenrl.common.errors import ConfigError

# users: (0.2, 0), (-0.2, 0), (0, 0), (0, +0.5233) left, (0, -0.5233) right
USERS_LEFT, USERS_RIGHT = 3, 4
# rich: v in (0.22, 0, -0.15) x w in (0, 0.5233, -0.5233, 1.4, -1.4); v = 0 is row 5-9
RICH_LEFT, RICH_RIGHT = 8, 9


def _seen(x, y):
    return np.array([1.0, x, y], np.float32)


def test_guard_action_on_the_detector_reading(make_bw):
    env = make_bw(opponents="idle", enemy_detector=True)
    assert env.guard_action(_seen(0.5, 0.05)) == -1                  # ahead, 6 deg off
    assert env.guard_action(_seen(0.0, 0.5)) == USERS_LEFT           # 90 deg on the left
    assert env.guard_action(_seen(0.0, -0.5)) == USERS_RIGHT         # 90 deg on the right
    assert env.guard_action(_seen(-0.5, 0.0)) == USERS_RIGHT         # straight behind: y = 0 turns right
    assert env.guard_action(_seen(0.5, 0.2)) == USERS_LEFT           # 21.8 deg off, inside 1.2 m
    assert env.guard_action(_seen(0.0, 1.3)) == -1                   # beyond 1.2 m
    assert env.guard_action(np.array([0.0, 0.0, 0.5], np.float32)) == -1  # not seen
    rich = make_bw(opponents="idle", enemy_detector=True, action_set="rich", face_radius=0.8, face_angle=30)
    assert rich.guard_action(_seen(0.0, 0.5)) == RICH_LEFT
    assert rich.guard_action(_seen(-0.3, -0.5)) == RICH_RIGHT
    assert rich.guard_action(_seen(0.5, 0.2)) == -1                  # 21.8 deg: inside 30
    assert rich.guard_action(_seen(0.0, 0.9)) == -1                  # beyond 0.8 m
    cont = make_bw(opponents="idle", enemy_detector=True, action_set="continuous")
    with pytest.raises(ValueError, match="discrete action set"):
        cont.guard_action(_seen(0.0, 0.5))


def test_guard_turns_a_robot_until_it_faces_the_other(make_bw):
    """Closed loop on real physics and the real detector: the other robot on my right at 0.5 m;
    following the guard turns me right until it is within 15 deg of my heading."""
    for side, k in (("red", 0), ("blue", 1)):
        env = make_bw(side=side, opponents="idle", lidar_noise=0.0, enemy_detector=True, action_set="rich")
        env.reset(seed=0)
        me, enemy = (-0.9, 0.0, math.pi / 2), (-0.4, 0.1, 0.0)
        env.set_poses(*((me, enemy) if k == 0 else (enemy, me)))
        obs = env.step(7)[0]  # (0, -0.5233): one slow turn on the spot, for a first reading
        first = env.guard_action(obs["enemy_seen"])
        assert first == RICH_RIGHT
        for _ in range(30):
            a = env.guard_action(obs["enemy_seen"])
            if a == -1:
                break
            assert a == RICH_RIGHT  # never overshoots into a left turn at 15 deg and 1.4 rad/s, 10 Hz
            obs = env.step(a)[0]
        else:
            pytest.fail("the guard did not bring the other robot within 15 deg of the heading in 30 steps")
        seen = obs["enemy_seen"]
        assert seen[0] == 1.0 and math.degrees(abs(math.atan2(seen[2], seen[1]))) <= 15.0


class _Inner:
    def __init__(self, n):
        self.n, self.synced, self.seeds = n, 0, []

    def act(self, obs):
        return np.full(self.n, 1, np.int64), np.arange(self.n * 2, dtype=np.float32).reshape(self.n, 2)

    def values(self, obs):
        return np.full(self.n, 7.0)

    def sync(self):
        self.synced += 1

    def reseed(self, seed):
        self.seeds.append(seed)


def test_demonstrated_replaces_where_the_rule_acts_at_its_share():
    shown = np.array([-1, 4, 0, -1], np.int64)
    rule = lambda obs: shown  # noqa: E731
    always = Demonstrated(_Inner(4), rule, 1.0, np.random.default_rng(0))
    a, extras = always.act({})
    assert a.tolist() == [1, 4, 0, 1] and always.taken == 2
    assert extras.tolist() == [[0, 1], [2, 3], [4, 5], [6, 7]]  # the Q values acted on, unchanged
    never = Demonstrated(_Inner(4), rule, 0.0, np.random.default_rng(0))
    assert never.act({})[0].tolist() == [1, 1, 1, 1] and never.taken == 0
    # a share of 0.3 over 2 x 5000 rule firings: within 5 sigma of 3000
    third = Demonstrated(_Inner(4), rule, 0.3, np.random.default_rng(1))
    for _ in range(5000):
        a, _ = third.act({})
        assert a[0] == 1 and a[3] == 1 and a[1] in (1, 4) and a[2] in (1, 0)
    assert abs(third.taken - 3000) < 5 * math.sqrt(10_000 * 0.3 * 0.7)
    # the rest passes through to the inner policy
    third.sync()
    third.reseed(5)
    assert third.inner.synced == 1 and third.inner.seeds == [5] and third.values({}).tolist() == [7.0] * 4
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        Demonstrated(_Inner(1), rule, 1.5, np.random.default_rng(0))


def test_guard_rule_over_a_batch_of_match_envs():
    kw = {"opponents": "idle", "side": "red", "lidar_noise": 0.0, "enemy_detector": True}
    envs = EnvBatch(EnvConfig(id="zenrl/BurgerWar-v0", kwargs=kw), 2, seed=0)
    try:
        rule = guard_rule(envs)
        obs = envs.reset()  # the actor's batched obs, as the policy gets them
        assert obs["obs/enemy_seen"].shape == (2, 3)
        obs["obs/enemy_seen"] = np.stack([_seen(0.0, 0.5), _seen(0.5, 0.0)])
        assert rule(obs).tolist() == [USERS_LEFT, -1]
    finally:
        envs.close()
    for cfg, what in ((EnvConfig(id="CartPole-v1"), "match env"),
                      (EnvConfig(id="zenrl/BurgerWar-v0", kwargs={"opponents": "idle"}), "enemy_detector"),
                      (EnvConfig(id="zenrl/BurgerWar-v0", kwargs={**kw, "flatten_obs": True}), "flatten_obs"),
                      (EnvConfig(id="zenrl/BurgerWar-v0", kwargs={**kw, "action_set": "continuous"}), "discrete")):
        envs = EnvBatch(cfg, 1, seed=0)
        try:
            with pytest.raises(ConfigError, match=what):
                guard_rule(envs)
        finally:
            envs.close()


@pytest.mark.parametrize("algo", ["r2d2", "a3c", "impala"])
@pytest.mark.parametrize("field,value", [("guard_share", "0.5"), ("cut_non_greedy", "true")])
def test_ape_x_options_are_refused_for_other_algorithms(algo, field, value):
    from zenrl.common.config import load_config

    with pytest.raises(Exception, match=f"actor.{field} is for algo apex, not {algo}"):
        load_config(None, [f"algo={algo}", f"actor.{field}={value}"], environ={})
    assert getattr(load_config(None, [f"actor.{field}={value}"], environ={}).actor, field)
