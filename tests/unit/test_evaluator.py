"""The evaluator's episode player: returns, and win/draw/loss outcomes for match envs."""

import numpy as np
import pytest
import torch

from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.evaluator import build_policy_net, play_episodes
from zenrl.common.networks import NumpyQ
from zenrl.common.config import RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.networks import flat_obs
from zenrl.common.policy_io import greedy_actions
from zenrl.games.burgerwar.judge import match_outcome


def _cfg(env: dict) -> RunConfig:
    return RunConfig.model_validate({"env": env, "network": {"hidden": [16]}})


def test_cartpole_has_returns_and_no_outcomes():
    cfg = _cfg({"id": "CartPole-v1"})
    envs = EnvBatch(cfg.env, 3, seed=0)
    torch.manual_seed(0)
    net = build_policy_net(cfg, envs)
    rets, outcomes = play_episodes(net, envs, seed=5)
    assert rets.shape == (3,) and rets.dtype == np.float32 and (rets >= 1).all()
    assert outcomes is None
    envs.close()


@pytest.mark.parametrize("algo", ["apex", "a3c"])
def test_numpy_forward_plays_the_same_episodes_as_torch(algo):
    cfg = _cfg({"id": "CartPole-v1"})
    cfg = cfg.model_copy(update={"algo": algo})
    envs = EnvBatch(cfg.env, 4, seed=0)
    torch.manual_seed(3)
    net = build_policy_net(cfg, envs)
    fast = NumpyQ.of(net)
    assert fast is not None
    by_torch, _ = play_episodes(net, envs, seed=11)
    by_numpy, _ = play_episodes(net, envs, seed=11, fast=fast)
    np.testing.assert_array_equal(by_numpy, by_torch)
    with torch.no_grad():  # other weights: the numpy copy follows only after load()
        for p in net.parameters():
            p.add_(torch.randn_like(p))
    fast.load(net)
    np.testing.assert_array_equal(play_episodes(net, envs, seed=11, fast=fast)[0], play_episodes(net, envs, seed=11)[0])
    envs.close()


@pytest.mark.parametrize("seed", [0, 1])
def test_match_outcomes_equal_a_hand_played_match(seed):
    # 8 s matches against cheese: it reads its FriedShrimp after ~4 s, so some are lost
    cfg = _cfg({"id": "zenrl/BurgerWar-v0",
                "kwargs": {"opponents": "cheese", "side": "random", "control_hz": 5, "max_steps": 40}})
    envs = EnvBatch(cfg.env, 4, seed=0)
    torch.manual_seed(seed)
    net = build_policy_net(cfg, envs)
    rets, outcomes = play_episodes(net, envs, seed=10 * seed)
    assert outcomes is not None and outcomes.dtype == np.int8 and outcomes.shape == (4,)
    sign = {"win": 1, "draw": 0, "loss": -1}
    for i in range(4):
        env = make_env(cfg.env)
        obs, _ = env.reset(seed=10 * seed + i)
        total, done = 0.0, False
        while not done:
            a = greedy_actions(net, {k: v[None] for k, v in flat_obs(obs).items()})[0]
            obs, r, term, trunc, info = env.step(a)
            total += r
            done = term or trunc
        assert outcomes[i] == sign[match_outcome(info)[0]]
        assert rets[i] == pytest.approx(total, abs=1e-4)
        env.close()
    envs.close()
