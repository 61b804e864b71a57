"""An honest actor whose env misbehaves (EnvGuard, in every actor's EnvBatch): a step with NaN or
Inf is cut (truncated there, reward 0, the observation before it as its last), a finite observation
outside the env's bounds is clipped where the run checks them, a reward that is not one number or
beyond the run's bound stops the actor with a line naming the setting. Nothing of it reaches the
services, which would reject whole chunks and quarantine the actor."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest

from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.env_guard import RESET_RETRIES, EnvGuard, EnvLimits
from zenrl.common.config import EnvConfig, load_config
from zenrl.common.errors import ConfigError, EnvOutputError
from zenrl.common.roles import Supervisor


class Scripted(gym.Env):
    """Observation float32[2] in [-1, 1] (a Dict {"pos": that, "vel": unbounded float32[1]} with
    ``dict_obs``); step t gives obs (t/100, -t/100) and reward 1, except what ``script`` says:
    ``{t: {"obs": ..., "reward": ...}}`` for the env with seed ``target`` (t counts steps since
    that env was made). ``bad_resets``: resets of the target env that give NaN."""

    def __init__(self, script=None, target: int = 0, dict_obs: bool = False, bad_resets: int = 0) -> None:
        box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.dict_obs = dict_obs
        self.observation_space = (gym.spaces.Dict({"pos": box, "vel": gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)})
                                  if dict_obs else box)
        self.action_space = gym.spaces.Discrete(2)
        self.script, self.target, self.bad_resets = dict(script or {}), target, bad_resets
        self.t, self.me = 0, None

    def _obs(self, pos, vel=0.0):
        pos = np.asarray(pos, np.float32)
        return {"pos": pos, "vel": np.array([vel], np.float32)} if self.dict_obs else pos

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.me = seed
        if self.me == self.target and self.bad_resets > 0:
            self.bad_resets -= 1
            return self._obs([np.nan, 0.0]), {}
        return self._obs([0.0, 0.0]), {}

    def step(self, action):
        self.t += 1
        s = self.script.get(self.t) if self.me == self.target else None
        obs, reward = self._obs([self.t / 100, -self.t / 100]), 1.0
        if s:
            obs = s.get("obs", obs)
            reward = s.get("reward", reward)
        return obs, reward, False, False, {}


if "test/Scripted-v0" not in gym.registry:
    gym.register("test/Scripted-v0", entry_point=Scripted)


def batch(script=None, limits=EnvLimits(1e3, "replay.max_abs_reward", True), n=3, **kw) -> EnvBatch:
    envs = EnvBatch(EnvConfig(id="test/Scripted-v0", kwargs={"script": script or {}, **kw}), n, seed=0, limits=limits)
    envs.reset()
    return envs


def f32(*x):
    return np.array(x, np.float32)


def run(envs: EnvBatch, steps: int):
    return [envs.step(np.zeros(envs.num_envs, np.int64)) for _ in range(steps)]


@pytest.mark.parametrize("bad", [{"reward": float("nan")}, {"reward": float("inf")}, {"obs": np.array([0.5, np.nan], np.float32)},
                                 {"reward": np.float32("nan")}])
def test_a_step_with_nan_or_inf_is_cut_and_nothing_else_lost(bad):
    envs = batch({3: bad})
    res = run(envs, 5)
    third = res[2]
    # env 0: truncated at step 3 with reward 0, the observation of step 2 as the last one
    assert third.truncated.tolist() == [True, False, False] and not third.terminated.any()
    assert third.rewards.tolist() == [0.0, 1.0, 1.0]
    np.testing.assert_array_equal(third.next_obs["obs"][0], f32(0.02, -0.02))
    np.testing.assert_array_equal(third.next_obs["obs"][1:], np.stack([f32(0.03, -0.03)] * 2))  # the others' steps as given
    np.testing.assert_array_equal(third.obs["obs"][0], [0.0, 0.0])  # env 0 was reset
    assert third.ep_returns == [2.0] and third.ep_lengths == [3]
    for r in res:
        assert np.isfinite(r.rewards).all() and np.isfinite(r.next_obs["obs"]).all() and np.isfinite(r.obs["obs"]).all()
    assert envs.values() == {"env_steps_cut": 1, "env_obs_clipped": 0, "env_resets_retried": 0}


def test_inf_in_an_unbounded_field_is_cut_too():
    envs = batch({2: {"obs": {"pos": np.array([0.1, 0.1], np.float32), "vel": np.array([np.inf], np.float32)}}}, dict_obs=True)
    res = run(envs, 3)
    assert res[1].truncated.tolist() == [True, False, False]
    np.testing.assert_array_equal(res[1].next_obs["obs/vel"][0], [0.0])
    assert envs.values()["env_steps_cut"] == 1


def test_an_observation_outside_its_bounds_is_clipped_where_the_run_checks_them():
    over = np.array([1.5, -0.25], np.float32)
    envs = batch({2: {"obs": over}})
    res = run(envs, 3)
    np.testing.assert_array_equal(res[1].next_obs["obs"][0], [1.0, -0.25])  # that element to its bound only
    assert not res[1].truncated.any() and res[1].rewards.tolist() == [1.0] * 3
    np.testing.assert_array_equal(res[2].obs["obs"][0], f32(0.03, -0.03))
    assert envs.values() == {"env_steps_cut": 0, "env_obs_clipped": 1, "env_resets_retried": 0}
    # a run that does not check the bounds (replay.check_obs_bounds false) gets the values as given
    free = batch({2: {"obs": over}}, limits=EnvLimits(1e3, "replay.max_abs_reward", False))
    np.testing.assert_array_equal(run(free, 3)[1].next_obs["obs"][0], over)
    assert free.values()["env_obs_clipped"] == 0


def test_a_value_on_a_bound_that_float32_rounds_is_kept():
    space = gym.spaces.Box(np.float32(-0.1), 0.1, (1,), np.float32)  # 0.1 in float32 is just above 0.1
    g = EnvGuard("x", space, EnvLimits(None, "", True))
    top = np.array([[np.float32(0.1)]], np.float32)
    assert g.bad_rows({"obs": top}) is None
    assert g.bad_rows({"obs": np.array([[0.1001]], np.float32)}).tolist() == [0]


def test_a_nested_dict_leaf_is_clipped_alone():
    envs = batch({2: {"obs": {"pos": np.array([0.0, -3.0], np.float32), "vel": np.array([7.0], np.float32)}}}, dict_obs=True)
    res = run(envs, 2)
    np.testing.assert_array_equal(res[1].next_obs["obs/pos"][0], [0.0, -1.0])
    np.testing.assert_array_equal(res[1].next_obs["obs/vel"][0], [7.0])  # unbounded: kept


@pytest.mark.parametrize("reward, taken", [(np.array([2.5], np.float32), 2.5), (np.float64(0.5), 0.5), (True, 1.0),
                                           (np.array(3, np.int64), 3.0)])
def test_a_reward_of_one_element_is_taken_as_its_number(reward, taken):
    res = run(batch({1: {"reward": reward}}), 1)
    assert res[0].rewards[0] == taken


@pytest.mark.parametrize("reward, named", [(np.array([1.0, 2.0]), "an array of shape (2,)"), (None, "a NoneType"),
                                           ([], "an array of shape (0,)")])
def test_a_reward_that_is_not_one_number_stops_the_actor(reward, named):
    envs = batch({2: {"reward": reward}})
    run(envs, 1)
    with pytest.raises(EnvOutputError, match=r"env test/Scripted-v0 returned a reward that is " + named.replace("(", r"\(").replace(")", r"\)")):
        run(envs, 1)


def test_a_reward_beyond_the_runs_bound_stops_the_actor_naming_the_setting():
    envs = batch({2: {"reward": -4e9}})
    run(envs, 1)
    with pytest.raises(EnvOutputError, match=r"reward of -4e\+09, beyond replay.max_abs_reward = 1000.*Raise replay.max_abs_reward"):
        run(envs, 1)
    # no bound (A3C, or the run's checks off): taken as given
    free = batch({2: {"reward": -4e9}}, limits=EnvLimits())
    assert run(free, 2)[1].rewards[0] == np.float32(-4e9)


def test_a_reset_with_nan_is_tried_again_then_stops_the_actor():
    envs = batch(bad_resets=2)  # the first reset and one retry give NaN
    assert envs.values()["env_resets_retried"] == 2
    assert np.isfinite(run(envs, 1)[0].obs["obs"]).all()
    with pytest.raises(EnvOutputError, match=f"reset gave an observation with NaN or Inf {RESET_RETRIES + 1} times"):
        batch(bad_resets=RESET_RETRIES + 1)


def test_the_run_limits_follow_its_services_checks():
    cfg = load_config(None, [])
    assert EnvLimits.of(cfg) == EnvLimits(cfg.replay.max_abs_reward, "replay.max_abs_reward", True, "replay.check_obs_bounds")
    assert EnvLimits.of(load_config(None, ["replay.check_semantics=false"])) == EnvLimits()
    assert EnvLimits.of(load_config(None, ["replay.check_obs_bounds=false"])).check_bounds is False
    assert EnvLimits.of(load_config(None, ["algo=impala", "impala.max_abs_reward=5"])) == EnvLimits(
        5.0, "impala.max_abs_reward", True, "impala.check_obs_bounds")
    assert EnvLimits.of(load_config(None, ["algo=a3c"])) == EnvLimits()


def test_the_supervisor_lets_an_env_output_error_end_the_role():
    sup = Supervisor()

    def bad():
        raise EnvOutputError("env x returned a reward that is a NoneType")

    with pytest.raises(EnvOutputError):
        sup.call("step", bad)
    assert isinstance(EnvOutputError("x"), ConfigError)  # the role exits as on a configuration error (2)
    assert sup.call("step", lambda: 1 / 0) is None and sup.errors["ZeroDivisionError"] == 1


def test_the_launcher_warns_once_a_count_grows_and_not_more_often_than_its_period():
    from zenrl.launcher.display import TroubleWatch

    w = TroubleWatch(every_s=30.0)
    quiet = {"env_steps_cut": 0, "env_obs_clipped": 0, "env_resets_retried": 0, "rejected": 0, "reasons": {}}
    assert w.news(quiet, now=0.0) is None
    line = w.news({**quiet, "env_steps_cut": 3}, now=1.0)
    assert line == "the actors' envs misbehave: 3 steps cut for NaN or Inf (logs/actor-*.log say which and why)"
    assert w.news({**quiet, "env_steps_cut": 9}, now=20.0) is None  # within the period
    assert w.news({**quiet, "env_steps_cut": 3}, now=40.0) is None  # nothing new
    line = w.news({**quiet, "env_steps_cut": 3, "rejected": 40, "reasons": {"obs_bounds": 39, "spec": 1},
                   "quarantined": "actor-0"}, now=41.0)
    assert line == ("40 chunks or unrolls rejected (obs_bounds 39, spec 1); quarantined: actor-0 "
                    "(logs/replay*.log, logs/learner.log)")


class Shapeshifter(gym.Env):
    """Declares ``space``; every observation is ``make(t)`` (t: steps since reset, 0 at reset)."""

    def __init__(self, space=None, make=None) -> None:
        self.observation_space = space
        self.action_space = gym.spaces.Discrete(2)
        self.make, self.t = make, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.make(0), {}

    def step(self, action):
        self.t += 1
        return self.make(self.t), 0.0, False, False, {}


if "test/Shapeshifter-v0" not in gym.registry:
    # without gymnasium's passive checker, which asserts on a Dict's keys at the first reset only
    gym.register("test/Shapeshifter-v0", entry_point=Shapeshifter, disable_env_checker=True)


def shifter(space, make, n=2) -> EnvBatch:
    return EnvBatch(EnvConfig(id="test/Shapeshifter-v0", kwargs={"space": space, "make": make}), n, seed=0,
                    limits=EnvLimits(1e3, "replay.max_abs_reward", True))


BOX = gym.spaces.Box(-5.0, 5.0, (4,), np.float32)


def test_numbers_of_another_kind_are_cast_to_the_spaces_dtype():
    envs = shifter(BOX, lambda t: np.array([t, 0, -1, 2]))  # int64 for a float32 Box: the replay refused each chunk
    assert envs.reset()["obs"].dtype == np.float32
    res = envs.step(np.zeros(2, np.int64))
    assert res.next_obs["obs"].dtype == np.float32 and res.next_obs["obs"][0].tolist() == [1.0, 0.0, -1.0, 2.0]
    cells = shifter(gym.spaces.Discrete(5), lambda t: np.int32(t % 5))
    assert cells.reset()["obs"].dtype == np.int64 and cells.step(np.zeros(2, np.int64)).obs["obs"].tolist() == [1, 1]


@pytest.mark.parametrize("space, make, says", [
    (BOX, lambda t: np.zeros(5, np.float32), "gave observation obs of shape (5,); its observation_space says (4,)"),
    (gym.spaces.Box(0, 255, (8, 8, 3), np.uint8), lambda t: np.random.rand(8, 8, 3),
     "gave observation obs as floats; its observation_space says uint8"),
    (gym.spaces.Discrete(3), lambda t: 1.5, "gave observation obs as floats; its observation_space says int64"),
    (gym.spaces.Dict({"a": BOX}), lambda t: {"a": np.zeros(4, np.float32), "b": np.zeros(1, np.float32)},
     "gave observation obs/b, which its observation_space does not have"),
    (gym.spaces.Dict({"a": BOX, "b": BOX}), lambda t: {"a": np.zeros(4, np.float32)}, "gave no observation obs/b"),
])
def test_an_observation_unlike_its_space_stops_the_actor_naming_the_field(space, make, says):
    with pytest.raises(EnvOutputError, match=re.escape(f"env test/Shapeshifter-v0 {says}")):
        shifter(space, make).reset()


def test_observations_of_different_shapes_stop_the_actor():
    envs = shifter(BOX, lambda t: np.zeros(4 if t < 2 else 3 + t % 2, np.float32), n=1)
    envs.reset()
    envs.step(np.zeros(1, np.int64))
    with pytest.raises(EnvOutputError, match=r"gave observation obs of shape \(3,\)"):
        envs.step(np.zeros(1, np.int64))
    ragged = EnvBatch(EnvConfig(id="test/Shapeshifter-v0", kwargs={"space": BOX, "make": lambda t: np.zeros(4, np.float32)}),
                      2, seed=0)
    ragged.reset()
    ragged.envs[1].unwrapped.make = lambda t: np.zeros(3, np.float32)
    with pytest.raises(EnvOutputError, match="gave observations of different shapes"):
        ragged.step(np.zeros(2, np.int64))


def test_what_is_wrong_is_named_by_its_own_side_and_nan_first():
    space = gym.spaces.Dict({"a": gym.spaces.Box(-1.0, 1.0, (3,), np.float32), "b": gym.spaces.Box(-1.0, 1.0, (1,), np.float32)})
    g = EnvGuard("x", space, EnvLimits(None, "", True))
    fixed, notes, broken = g.fix({"a": np.array([2.0, 0.0, -3.0], np.float32), "b": np.array([0.5], np.float32)})
    assert not broken and notes == ["observation obs/a[0] = 2 is above the env's bound 1"]
    np.testing.assert_array_equal(fixed["a"], f32(1.0, 0.0, -1.0))
    _, notes, _ = g.fix({"a": np.array([0.0, 0.0, -3.0], np.float32), "b": np.array([0.5], np.float32)})
    assert notes == ["observation obs/a[2] = -3 is below the env's bound -1"]
    _, notes, broken = g.fix({"a": np.array([2.0, 0.0, 0.0], np.float32), "b": np.array([np.nan], np.float32)})
    assert broken and notes[0] == "observation obs/b holds NaN or Inf"


def test_the_launcher_says_once_when_no_episode_ends():
    from zenrl.launcher.display import Progress, endless_warning

    p = Progress()
    assert endless_warning(p, "x", now=1e9) is None  # no env step yet
    p.first_step_t = 100.0
    p.actor_steps["actor-0"] = 12345
    assert endless_warning(p, "x", now=150.0) is None  # not long enough
    line = endless_warning(p, "my:Env-v0", now=170.0)
    assert line == ("no episode has ended in 70 s (12,345 env steps): my:Env-v0's episodes may never end (no step "
                    "limit), and then no return is reported and no evaluation finishes; set env.max_episode_steps")
    p.recent_returns.append(3.0)
    assert endless_warning(p, "x", now=170.0) is None
