"""Observations reach the wire in the dtypes the env's spec names (``obs_fields``: a uint8 Box
stays uint8, any other Box is float32, a Discrete is int64): an env with an int64 or float64 Box,
or a MultiBinary, is wrapped so that what the actors send is what the replay checks against."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from tests.integration import custom_envs  # noqa: F401  (registers IntWalk-v0)
from zenrl.actor.batch_env import EnvBatch
from zenrl.common.config import EnvConfig
from zenrl.common.env_factory import WireObservations, make_env
from zenrl.common.networks import obs_spec


class _SampledEnv(gym.Env):
    """Observations sampled from its ``observation_space`` (set by a subclass), two actions."""

    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


class _MixedEnv(_SampledEnv):
    """A Dict of an int32 Box, a float64 Box, a MultiBinary, a Discrete and a uint8 image."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Dict({
            "count": gym.spaces.Box(0, 10, (3,), np.int32), "pos": gym.spaces.Box(-1.0, 1.0, (2,), np.float64),
            "flags": gym.spaces.MultiBinary(4), "cell": gym.spaces.Discrete(5),
            "image": gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)})


if "test/MixedObs-v0" not in gym.registry:
    gym.register("test/MixedObs-v0", entry_point=_MixedEnv, max_episode_steps=10)


@pytest.mark.parametrize("env_id", ["IntWalk-v0", "test/MixedObs-v0"])
def test_what_the_actors_stack_has_the_dtypes_of_the_spec(env_id):
    batch = EnvBatch(EnvConfig(id=env_id), 3, seed=0)
    spec = obs_spec(batch.single_observation_space)  # what the replay's checks hold chunks to
    for obs in (batch.reset(), batch.step(np.array([1, 0, 1])).next_obs):
        assert {k: v.dtype.name for k, v in obs.items()} == {k: s.dtype for k, s in spec.items()}
        assert {k: v.shape[1:] for k, v in obs.items()} == {k: s.shape for k, s in spec.items()}


def test_the_wire_space_keeps_the_bounds_and_the_kinds():
    env = make_env(EnvConfig(id="test/MixedObs-v0"))
    assert isinstance(env, WireObservations)
    sp = env.observation_space
    assert sp["count"] == gym.spaces.Box(0, 10, (3,), np.float32)
    assert sp["pos"] == gym.spaces.Box(-1, 1, (2,), np.float32)
    assert sp["flags"] == gym.spaces.Box(0, 1, (4,), np.float32)
    assert sp["cell"] == gym.spaces.Discrete(5) and sp["image"] == gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)
    assert obs_spec(sp)["obs/cell"].categories == (0, 5)
    obs, _ = env.reset(seed=1)
    assert obs["count"].dtype == np.float32 and set(np.unique(obs["flags"])) <= {0.0, 1.0}
    assert sp.contains(obs)


@pytest.mark.parametrize("env_id", ["CartPole-v1", "FrozenLake-v1", "zenrl/StatelessCartPole-v1"])
def test_envs_already_in_the_wire_dtypes_are_not_wrapped(env_id):
    env = make_env(EnvConfig(id=env_id))
    assert not isinstance(env, WireObservations)
    w = env
    while hasattr(w, "env"):
        assert not isinstance(w, WireObservations)
        w = w.env


class _NestedEnv(_SampledEnv):
    """A Tuple of a float64 Box, a MultiDiscrete with starts and a Dict holding a Tuple."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Tuple((
            gym.spaces.Box(-2.0, 2.0, (2,), np.float64),
            gym.spaces.MultiDiscrete([3, 4], start=[-1, 5]),
            gym.spaces.Dict({"inner": gym.spaces.Tuple((gym.spaces.Discrete(2), gym.spaces.MultiBinary(3)))})))


if "test/NestedObs-v0" not in gym.registry:
    gym.register("test/NestedObs-v0", entry_point=_NestedEnv, max_episode_steps=10)


def test_a_tuple_observation_becomes_a_dict_of_its_members():
    """Blackjack's Tuple(Discrete(32), Discrete(11), Discrete(2)): three one-hot fields, the
    values as the env gave them."""
    env = make_env(EnvConfig(id="Blackjack-v1"))
    assert env.observation_space == gym.spaces.Dict({"0": gym.spaces.Discrete(32), "1": gym.spaces.Discrete(11),
                                                     "2": gym.spaces.Discrete(2)})
    spec = obs_spec(env.observation_space)
    assert {k: s.categories for k, s in spec.items()} == {"obs/0": (0, 32), "obs/1": (0, 11), "obs/2": (0, 2)}
    obs, _ = env.reset(seed=3)
    raw = env.unwrapped._get_obs()  # the env's own tuple for the same state
    assert obs == {"0": raw[0], "1": raw[1], "2": raw[2]} and env.observation_space.contains(obs)


def test_nested_tuples_and_multidiscrete_keep_their_values_and_starts():
    env = make_env(EnvConfig(id="test/NestedObs-v0"))
    sp = env.observation_space
    assert sp["0"] == gym.spaces.Box(-2, 2, (2,), np.float32)
    assert sp["1"] == gym.spaces.Dict({"0": gym.spaces.Discrete(3, start=-1), "1": gym.spaces.Discrete(4, start=5)})
    assert sp["2"]["inner"]["0"] == gym.spaces.Discrete(2) and sp["2"]["inner"]["1"] == gym.spaces.Box(0, 1, (3,), np.float32)
    spec = obs_spec(sp)
    assert spec["obs/1/0"].categories == (-1, 3) and spec["obs/1/1"].categories == (5, 4)
    inner = env.env  # the env before the wrapper, to compare values
    obs, _ = env.reset(seed=0)
    assert sp.contains(obs)
    for _ in range(20):
        obs, *_ = env.step(0)
        assert sp.contains(obs)
    raw = inner.observation_space.sample()
    cast = env.observation(raw)
    np.testing.assert_array_equal(cast["0"], raw[0].astype(np.float32))
    assert (int(cast["1"]["0"]), int(cast["1"]["1"])) == (int(raw[1][0]), int(raw[1][1]))
    assert int(cast["2"]["inner"]["0"]) == int(raw[2]["inner"][0])
    np.testing.assert_array_equal(cast["2"]["inner"]["1"], raw[2]["inner"][1].astype(np.float32))
    batch = EnvBatch(EnvConfig(id="test/NestedObs-v0"), 3, seed=0)  # what an actor stacks: the spec's dtypes
    obs = batch.reset()
    assert {k: v.dtype.name for k, v in obs.items()} == {k: s.dtype for k, s in spec.items()}


def test_an_unsupported_member_is_named():
    space = gym.spaces.Tuple((gym.spaces.Discrete(2), gym.spaces.Text(5)))
    with pytest.raises(ValueError, match="Text.*is not supported .*Tuple"):
        obs_spec(space)
