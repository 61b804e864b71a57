"""The evaluator's rounds (actor/evaluator.py): returns, win/draw/loss outcomes for match envs,
and the numpy route to the greedy actions playing what torch plays."""

import numpy as np
import pytest
import torch

from tests.unit.actor_fakes import FakeNode, step_until, weights_payload
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.evaluator import Evaluator, build_policy_net
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.networks import flat_obs
from zenrl.common.policy_io import greedy_actions
from zenrl.games.burgerwar.judge import match_outcome


def _cfg(env: dict, episodes: int, seed: int = 0, **top) -> RunConfig:
    return RunConfig.model_validate({"env": env, "network": {"hidden": [16]}, "seed": seed, **top,
                                     "evaluator": {"episodes": episodes, "seed_offset": 0, "interval_s": 0.01}})


def _trained(cfg: RunConfig, seed: int) -> torch.nn.Module:
    """A policy network as a learner would broadcast it (weights from ``seed``)."""
    envs = EnvBatch(cfg.env, 1, seed=0)
    torch.manual_seed(seed)
    net = build_policy_net(cfg, envs)
    envs.close()
    return net


def _rounds(cfg: RunConfig, nets: list, use_numpy: bool = True) -> list[P.EvalResult]:
    """One evaluation round per network in ``nets`` (broadcast as versions 1, 2, ...)."""
    node = FakeNode(weights_payload(nets[0], version=1))
    ev = Evaluator(cfg, node, "t", use_numpy=use_numpy)
    assert (ev.policy.q.fast is not None) == use_numpy
    ev.start(node)
    out = []
    for v, net in enumerate(nets, start=1):
        if v > 1:
            node.latest.set("k", weights_payload(net, version=v))
        step_until(ev, lambda: len(node.sent(P.Keys("t").eval)) == v)
        out.append(P.EvalResult.decode(node.sent(P.Keys("t").eval)[-1]))
        assert out[-1].version == v
    ev.close()
    return out


def test_cartpole_has_returns_and_no_outcomes():
    cfg = _cfg({"id": "CartPole-v1"}, 3)
    (r,) = _rounds(cfg, [_trained(cfg, 0)])
    assert r.returns.shape == (3,) and r.returns.dtype == np.float32 and (r.returns >= 1).all()
    assert r.outcomes is None


@pytest.mark.parametrize("algo", ["apex", "a3c"])
def test_numpy_forward_plays_the_same_episodes_as_torch(algo):
    cfg = _cfg({"id": "CartPole-v1"}, 4, algo=algo)
    first = _trained(cfg, 3)
    other = _trained(cfg, 3)
    with torch.no_grad():  # other weights: the numpy copy must follow the load
        for p in other.parameters():
            p.add_(torch.randn_like(p))
    by_numpy = _rounds(cfg, [first, other], use_numpy=True)
    by_torch = _rounds(cfg, [first, other], use_numpy=False)
    for a, b in zip(by_numpy, by_torch):
        np.testing.assert_array_equal(a.returns, b.returns)
    assert not np.array_equal(by_numpy[0].returns, by_numpy[1].returns), "the second round plays other weights"


@pytest.mark.parametrize("seed", [0, 1])
def test_match_outcomes_equal_a_hand_played_match(seed):
    # 8 s matches against cheese: it reads its FriedShrimp after ~4 s, so some are lost
    cfg = _cfg({"id": "zenrl/BurgerWar-v0",
                "kwargs": {"opponents": "cheese", "side": "random", "control_hz": 5, "max_steps": 40}}, 4, seed=10 * seed)
    net = _trained(cfg, seed)
    (r,) = _rounds(cfg, [net])
    rets, outcomes = r.returns, r.outcomes
    assert outcomes is not None and outcomes.dtype == np.int8 and outcomes.shape == (4,)
    sign = {"win": 1, "draw": 0, "loss": -1}
    for i in range(4):  # round 0 plays env i on seed + seed_offset + i
        env = make_env(cfg.env)
        obs, _ = env.reset(seed=10 * seed + i)
        total, done = 0.0, False
        while not done:
            a = greedy_actions(net, {k: v[None] for k, v in flat_obs(obs).items()})[0]
            obs, rew, term, trunc, info = env.step(a)
            total += rew
            done = term or trunc
        assert outcomes[i] == sign[match_outcome(info)[0]]
        assert rets[i] == pytest.approx(total, abs=1e-4)
        env.close()
