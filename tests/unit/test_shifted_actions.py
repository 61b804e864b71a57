"""An env whose actions are ``Discrete(n, start)`` with ``start != 0`` (e.g. -1, 0, +1 for left,
stay, right) is played by index: the networks, the wire and the replay's checks see 0..n-1, the
env gets ``start + index``; an exported policy returns the env's own action."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from tests.integration import custom_envs  # noqa: F401  (registers ShiftWalk-v0)
from tests.unit.test_tools import load_exported, make_checkpoint
from zenrl import tools
from zenrl.actor.batch_env import EnvBatch
from zenrl.common.config import EnvConfig
from zenrl.common.env_factory import ShiftedActions, make_env
from zenrl.common.policy_io import ExportedPlayer, load_policy, single_to_flat


def test_the_env_gets_start_plus_the_index():
    env = make_env(EnvConfig(id="ShiftWalk-v0"))
    assert isinstance(env, ShiftedActions) and env.action_space == gym.spaces.Discrete(3)
    env.reset(seed=0)
    for index in (2, 2, 0, 1, 2):
        env.step(np.int64(index))
    assert env.unwrapped.moves == [1, 1, -1, 0, 1]
    # the index an actor picks past the env's last action is refused by the env, not shifted into it
    with pytest.raises(ValueError, match="not in Discrete"):
        env.step(3)
    env.close()


def test_an_actor_batch_plays_every_action_of_the_env():
    envs = EnvBatch(EnvConfig(id="ShiftWalk-v0"), 2, seed=3)
    assert envs.single_action_space == gym.spaces.Discrete(3)
    envs.reset()
    for _ in range(20):  # env 0 reaches 5 (and resets) every 5 steps; env 1 stays at -5
        envs.step(np.array([2, 0]))
    moves = [e.unwrapped.moves for e in envs.envs]
    assert moves[0] == [1] * 20 and moves[1] == [-1] * 20
    for e in envs.envs:
        e.close()


@pytest.mark.parametrize("env_id, wrapped", [("CartPole-v1", False), ("FrozenLake-v1", False)])
def test_envs_whose_actions_start_at_zero_are_not_wrapped(env_id, wrapped):
    env = make_env(EnvConfig(id=env_id))
    assert isinstance(env, ShiftedActions) is wrapped
    env.close()


def test_export_returns_the_envs_action_and_the_player_the_index(tmp_path):
    ckpt = make_checkpoint(tmp_path / "c", "ShiftWalk-v0", {})
    out = tmp_path / "policy.pt"
    meta = tools.export(str(ckpt), str(out))
    assert meta["action_start"] == -1 and meta["n_actions"] == 3
    env = make_env(EnvConfig(id="ShiftWalk-v0"))
    policy = load_policy(ckpt, env.observation_space, env.action_space)
    observations = [np.array([x], np.float32) for x in np.linspace(-5, 5, 41)]
    index = [int(policy.batch(single_to_flat(o))[0]) for o in observations]
    assert len(set(index)) > 1  # the comparison is not trivially constant
    ts, meta_in_file = load_exported(out)
    assert meta_in_file["action_start"] == -1
    assert [int(ts(torch.as_tensor(o))) for o in observations] == [i - 1 for i in index]
    player = ExportedPlayer(out)
    player.check_spaces(env.observation_space, env.action_space)
    assert [player(o) for o in observations] == index
    env.close()
