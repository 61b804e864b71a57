"""``zenrl/StatelessCartPole-v1``: CartPole-v1 with the velocities hidden, the partially
observable yardstick for recurrent agents (R2D2).

The observation is float32[2]: cart position and pole angle (CartPole's components 0 and 2),
with CartPole's bounds for them; the cart velocity and the pole's angular velocity (components 1
and 3) must be inferred from the history. Dynamics, rewards, termination and the 500-step limit
are CartPole-v1's, unchanged: the same seed and actions give the same positions and angles.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control.cartpole import CartPoleEnv

#: the components of CartPole's observation that stay visible: x and theta
VISIBLE = np.array([0, 2])


class StatelessCartPoleEnv(CartPoleEnv):
    """CartPoleEnv whose observations are ``obs[[0, 2]]`` (options as CartPoleEnv's)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        full = self.observation_space
        self.observation_space = gym.spaces.Box(full.low[VISIBLE], full.high[VISIBLE], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return obs[VISIBLE], info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs[VISIBLE], reward, terminated, truncated, info
