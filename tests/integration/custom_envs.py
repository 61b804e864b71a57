"""Environments a user might write, for tests that run them under ``zenrl run`` (``env.id`` as
``tests.integration.custom_envs:<id>``: gymnasium imports this module, which registers them).

* ``IntWalk-v0``: a walk on 0..9 from 0, +1 for reaching 9; the observation an int64 ``Box``
  ``[position, steps taken]`` (what a grid or a counter gives), actions left / right."""

from __future__ import annotations

import gymnasium as gym
import numpy as np


class IntWalkEnv(gym.Env):
    """A walk on 0..9; observation int64[2] = (position, steps taken); reaching 9 gives +1 and ends
    the episode; 50 steps at most."""

    def __init__(self, dtype: str = "int64") -> None:
        self.dt = np.dtype(dtype)
        self.observation_space = gym.spaces.Box(0, 100, (2,), self.dt)
        self.action_space = gym.spaces.Discrete(2)
        self.pos = self.t = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.pos, self.t], self.dt)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.pos = min(9, max(0, self.pos + (1 if int(action) == 1 else -1)))
        self.t += 1
        done = self.pos == 9
        return self._obs(), float(done), done, False, {}


if "IntWalk-v0" not in gym.registry:
    gym.register("IntWalk-v0", entry_point=IntWalkEnv, max_episode_steps=50)
