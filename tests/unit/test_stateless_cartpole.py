"""zenrl/StatelessCartPole-v1: CartPole-v1's dynamics with only x and theta observed."""

import gymnasium as gym
import numpy as np

import zenrl.common.envs  # noqa: F401  (registers the zenrl/ envs)
from zenrl.common.config import EnvConfig
from zenrl.common.env_factory import make_env


def test_observation_space_is_position_and_angle():
    env = gym.make("zenrl/StatelessCartPole-v1")
    full = gym.make("CartPole-v1")
    space = env.observation_space
    assert space.shape == (2,) and space.dtype == np.float32
    np.testing.assert_array_equal(space.low, full.observation_space.low[[0, 2]])
    np.testing.assert_array_equal(space.high, full.observation_space.high[[0, 2]])
    assert np.isfinite(space.low).all() and space.high[0] == 4.8
    assert env.action_space == full.action_space
    assert env.spec.max_episode_steps == 500 and env.spec.reward_threshold == 475.0
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2,) and obs.dtype == np.float32 and space.contains(obs)


def test_dynamics_are_cartpoles():
    """Same seed and actions: the same x and theta as CartPole-v1's components 0 and 2, the same
    rewards and episode ends, over several episodes (one reset seed, then unseeded resets)."""
    env = make_env(EnvConfig(id="zenrl/StatelessCartPole-v1"))
    ref = gym.make("CartPole-v1")
    rng = np.random.default_rng(0)
    o, _ = env.reset(seed=123)
    r, _ = ref.reset(seed=123)
    np.testing.assert_array_equal(o, r[[0, 2]])
    assert not np.array_equal(r[[0, 2]], r[[0, 1]])  # the comparison picks the right columns
    episodes = 0
    for _ in range(600):
        a = int(rng.integers(2))
        o, rew, te, tr, _ = env.step(a)
        r, rew_r, te_r, tr_r, _ = ref.step(a)
        np.testing.assert_array_equal(o, r[[0, 2]])
        assert (rew, te, tr) == (rew_r, te_r, tr_r)
        if te or tr:
            episodes += 1
            o, _ = env.reset()
            r, _ = ref.reset()
            np.testing.assert_array_equal(o, r[[0, 2]])
    assert episodes >= 5
