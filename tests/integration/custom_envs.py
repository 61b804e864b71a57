"""Environments a user might write, for tests that run them under ``zenrl run`` (``env.id`` as
``tests.integration.custom_envs:<id>``: gymnasium imports this module, which registers them).

* ``IntWalk-v0``: a walk on 0..9 from 0, +1 for reaching 9; the observation an int64 ``Box``
  ``[position, steps taken]`` (what a grid or a counter gives), actions left / right.
* ``ShiftWalk-v0``: a walk on -5..5 from 0, +1 for reaching 5; actions ``Discrete(3, start=-1)``
  (left, stay, right: the move itself), checked by the env (an action outside them raises).
* ``NestedDict-v0``: a Dict inside a Dict (``{"arm": {"joints", "grip"}, "cell": Discrete}``);
  reward 1 for action 1."""

from __future__ import annotations

import fcntl
import time

import gymnasium as gym
import numpy as np


class IntWalkEnv(gym.Env):
    """A walk on 0..9; observation int64[2] = (position, steps taken); reaching 9 gives +1 (or
    ``goal_reward``) and ends the episode; 50 steps at most. A faulty env on request: every
    ``nan_every``-th step of the env gives a NaN reward, every ``over_every``-th an observation
    whose step count (150) is above its bound (100); with ``obs_size`` another number of
    observation values than its space's 2; with ``hang_after_s`` the env reset with seed
    ``hang_seed`` never returns from its first step that many seconds after it was made (a
    simulator that hangs); with ``one_client`` (a file path) the env is made only while no other
    env of it is open: its constructor waits for an ``flock`` on that file, ``close`` lets go (a
    simulator that takes one client at a time)."""

    metadata = {"render_modes": ["rgb_array"]}  # claimed, not drawn: render() is gym.Env's

    def __init__(self, dtype: str = "int64", nan_every: int = 0, over_every: int = 0, goal_reward: float = 1.0,
                 render_mode: str | None = None, obs_size: int = 2, hang_after_s: float = 0.0, hang_seed: int = -1,
                 one_client: str = "") -> None:
        self.client = None
        if one_client:
            self.client = open(one_client, "a")
            fcntl.flock(self.client, fcntl.LOCK_EX)
        self.render_mode = render_mode
        self.dt = np.dtype(dtype)
        self.observation_space = gym.spaces.Box(0, 100, (2,), self.dt)
        self.action_space = gym.spaces.Discrete(2)
        self.pos = self.t = 0
        self.nan_every, self.over_every, self.goal_reward = nan_every, over_every, goal_reward
        self.obs_size = obs_size
        self.hang_after_s, self.hang_seed, self.seeded = hang_after_s, hang_seed, None
        self.made = time.monotonic()
        self.steps = 0

    def _obs(self) -> np.ndarray:
        return np.resize(np.array([self.pos, self.t], self.dt), self.obs_size)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.seeded = seed
        self.pos = self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.pos = min(9, max(0, self.pos + (1 if int(action) == 1 else -1)))
        self.t += 1
        self.steps += 1
        if self.hang_after_s and self.seeded == self.hang_seed and time.monotonic() - self.made > self.hang_after_s:
            time.sleep(1e6)
        done = self.pos == 9
        obs, reward = self._obs(), self.goal_reward if done else 0.0
        if self.over_every and self.steps % self.over_every == 0:
            obs[1] = 150
        if self.nan_every and self.steps % self.nan_every == 0:
            reward = float("nan")
        return obs, reward, done, False, {}

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None


if "IntWalk-v0" not in gym.registry:
    gym.register("IntWalk-v0", entry_point=IntWalkEnv, max_episode_steps=50)


class ShiftWalkEnv(gym.Env):
    """A walk on -5..5 from 0; observation float32[1] = position; action -1, 0 or +1
    (``Discrete(3, start=-1)``), an action outside them raises; reaching 5 gives +1 and ends
    the episode. ``moves`` records the actions the env was given."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-5.0, 5.0, (1,), np.float32)
        self.action_space = gym.spaces.Discrete(3, start=-1)
        self.pos = 0
        self.moves: list[int] = []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = 0
        return np.array([self.pos], np.float32), {}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not in {self.action_space}")
        self.moves.append(int(action))
        self.pos = min(5, max(-5, self.pos + int(action)))
        done = self.pos == 5
        return np.array([self.pos], np.float32), float(done), done, False, {}


if "ShiftWalk-v0" not in gym.registry:
    gym.register("ShiftWalk-v0", entry_point=ShiftWalkEnv, max_episode_steps=40)


class NestedDictEnv(gym.Env):
    """Observation ``{"arm": {"joints": float32[3], "grip": int32 Box[1]}, "cell": Discrete(4)}``
    (random), two actions, reward 1 for action 1, 20 steps an episode."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Dict({
            "arm": gym.spaces.Dict({"joints": gym.spaces.Box(-1.0, 1.0, (3,), np.float32),
                                    "grip": gym.spaces.Box(0, 5, (1,), np.int32)}),
            "cell": gym.spaces.Discrete(4)})
        self.action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), float(int(action) == 1), False, False, {}


if "NestedDict-v0" not in gym.registry:
    gym.register("NestedDict-v0", entry_point=NestedDictEnv, max_episode_steps=20)
