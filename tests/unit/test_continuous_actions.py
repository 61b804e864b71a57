"""Continuous (Box) actions for IMPALA / APPO: the env's actions normalised to [-1, 1], the
Gaussian actor-critic and its numpy forward, the actors' sampling and its log-densities against
the normal density written out by hand, greedy acting, and what the learner's unroll checks take
and refuse. (The learner's step on continuous actions: tests/unit/test_impala_loss.py.)"""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from zenrl.actor.policies import Greedy, Sampling
from zenrl.common import protocol as P
from zenrl.common.config import EnvConfig, NetworkConfig
from zenrl.common.env_factory import make_env
from zenrl.common.networks import (LOG_STD_MAX, LOG_STD_MIN, ActorCritic, BoxActions, NumpyQ, action_size,
                                   num_actions, policy_actions, to_tensors)
from zenrl.common.specs import ArraySpec
from zenrl.common.unroll_checks import MAX_ABS_ACTION, UnrollChecker

SPEC = {"obs": ArraySpec((3,), "float32")}
OBS_SPACE = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
T = 5


def _net(d=2, log_std_init=-0.5, hidden=(8,)):
    torch.manual_seed(3)
    return ActorCritic(SPEC, BoxActions(d), NetworkConfig(hidden=list(hidden), log_std_init=log_std_init))


# -- the env's side ---------------------------------------------------------------------------
def test_pendulum_actions_are_normalised_and_clipped():
    env = make_env(EnvConfig(id="Pendulum-v1"))
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    env.reset(seed=0)
    for a, torque in ((0.5, 1.0), (-1.0, -2.0), (0.0, 0.0), (3.0, 2.0), (-7.5, -2.0)):
        env.step(np.array([a], np.float32))
        assert env.unwrapped.last_u == pytest.approx(torque), a  # Pendulum's bounds are [-2, 2]
    env.close()


def test_an_integer_box_gets_the_nearest_integer():
    from zenrl.common.env_factory import NormalisedActions

    class IntBox(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        action_space = gym.spaces.Box(-2, 2, (3,), np.int64)

    env = NormalisedActions(IntBox())
    # [-1, 1] onto [-2, 2]: 0.2 -> 0.4, 0.3 -> 0.6, -0.8 -> -1.6: the nearest integers, not toward 0
    got = env.action(np.array([0.2, 0.3, -0.8], np.float32))
    assert got.dtype == np.int64 and got.tolist() == [0, 1, -2]


def test_other_action_spaces_are_left_alone():
    env = make_env(EnvConfig(id="CartPole-v1"))
    assert env.action_space == gym.spaces.Discrete(2)
    env.close()


def test_policy_size_per_space_and_algorithm():
    box = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    assert policy_actions(box) == 3 and isinstance(policy_actions(box), BoxActions)
    assert policy_actions(gym.spaces.Discrete(4)) == 4 and not isinstance(policy_actions(gym.spaces.Discrete(4)), BoxActions)
    assert isinstance(action_size(box, "impala"), BoxActions) and isinstance(action_size(box, "a3c"), BoxActions)
    for algo in ("apex", "r2d2"):
        with pytest.raises(ValueError, match=f"algo: {algo} needs a Discrete action space.*algo: impala"):
            action_size(box, algo)
    with pytest.raises(ValueError, match="1-D Box"):
        policy_actions(gym.spaces.Box(-1.0, 1.0, (2, 2), np.float32))
    with pytest.raises(ValueError, match="finite bounds"):
        policy_actions(gym.spaces.Box(-np.inf, np.inf, (2,), np.float32))
    with pytest.raises(ValueError, match="Discrete action space"):
        num_actions(gym.spaces.MultiDiscrete([2, 3]))


# -- the network --------------------------------------------------------------------------------
def test_gaussian_actor_critic_means_and_numpy_forward():
    net = _net(d=2)
    assert net.continuous and net.log_std.shape == (2,) and torch.all(net.log_std == -0.5)
    x = np.random.default_rng(0).normal(scale=30.0, size=(64, 3)).astype(np.float32)
    with torch.no_grad():
        mean, value = net(to_tensors({"obs": x}))
    assert mean.shape == (64, 2) and value.shape == (64,)
    assert float(mean.abs().max()) <= 1.0  # tanh: inside the range the env clips to
    np.testing.assert_allclose(NumpyQ.of(net)({"obs": x}), mean.numpy(), rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        net.log_std.fill_(9.0)
    assert torch.all(net.clamped_log_std() == LOG_STD_MAX)


# -- acting ---------------------------------------------------------------------------------------
def _normal_logpdf(a, mean, sd):
    return sum(-0.5 * ((a[j] - mean[j]) / sd[j]) ** 2 - math.log(sd[j]) - 0.5 * math.log(2 * math.pi)
               for j in range(len(a)))


def test_sampling_draws_around_the_mean_with_the_density_it_reports():
    net = _net(d=2, log_std_init=-1.5)
    pol = Sampling(net, 2, np.random.default_rng(0), use_numpy=True, with_logp=True)
    obs = {"obs": np.tile(np.array([[0.3, -0.2, 0.9]], np.float32), (20_000, 1))}
    a, logp = pol.act(obs)
    assert a.dtype == np.float32 and a.shape == (20_000, 2) and logp.dtype == np.float32 and logp.shape == (20_000,)
    mean = NumpyQ.of(net)(obs)[0].astype(np.float64)
    sd = np.exp(np.full(2, -1.5))
    np.testing.assert_allclose(a.mean(0), mean, atol=0.02)
    np.testing.assert_allclose(a.std(0), sd, rtol=0.03)
    for i in range(5):
        assert logp[i] == pytest.approx(_normal_logpdf(a[i].astype(np.float64), mean, sd), rel=1e-5, abs=1e-5)
    assert (logp > 0).any()  # a density, not a probability: narrow Gaussians exceed 1


def test_sampling_follows_the_log_std_after_a_weights_load():
    net = _net(d=1, log_std_init=0.0)
    pol = Sampling(net, 1, np.random.default_rng(1), use_numpy=True, with_logp=True)
    with torch.no_grad():
        net.log_std.fill_(LOG_STD_MIN - 3)  # used clamped
    pol.sync()
    a, _ = pol.act({"obs": np.zeros((5_000, 3), np.float32)})
    assert a.std() == pytest.approx(math.exp(LOG_STD_MIN), rel=0.05)


def test_epsilon_cannot_come_with_behaviour_densities():
    with pytest.raises(ValueError, match="epsilon"):
        Sampling(_net(), 2, np.random.default_rng(0), epsilon=0.1, with_logp=True)


def test_greedy_acts_on_the_mean_and_explores_inside_the_box():
    net = _net(d=3)
    x = {"obs": np.random.default_rng(2).normal(size=(7, 3)).astype(np.float32)}
    with torch.no_grad():
        mean = net(to_tensors(x))[0].numpy()
    for use_numpy in (True, False):
        a, extras = Greedy(net, 3, use_numpy=use_numpy).act(x)
        assert extras is None and a.dtype == np.float32
        np.testing.assert_allclose(a, mean, rtol=1e-5, atol=1e-6)
    a, _ = Greedy(net, 3, epsilon=1.0, seed=0).act(x)
    assert a.shape == (7, 3) and np.abs(a).max() <= 1.0 and not np.allclose(a, mean)


# -- the learner's checks ---------------------------------------------------------------------
def _checker(d=2):
    return UnrollChecker.from_spaces(OBS_SPACE, gym.spaces.Box(-2.0, 2.0, (d,), np.float32), max_abs_reward=10.0,
                                     unroll_length=T)


def _unroll(**over):
    rng = np.random.default_rng(0)
    kw = dict(actor_id="a0", policy_version=1, seq=0, obs={"obs": np.zeros((T + 1, 3), np.float32)},
              action=rng.normal(scale=1.5, size=(T, 2)).astype(np.float32),
              behaviour_logp=np.array([-1.0, 0.5, 3.0, -20.0, 0.0], np.float32), reward=np.ones(T, np.float32),
              terminated=np.zeros(T, bool), truncated=np.zeros(T, bool), final_obs=None)
    kw.update(over)
    return P.Unroll(**kw)


def _reason(u, checker=None):
    bad = (checker or _checker()).check(u)
    return None if bad is None else bad.reason


def test_checks_take_an_honest_continuous_unroll():
    assert _checker().continuous and _checker().n_actions == 2
    assert _reason(_unroll()) is None
    # the narrowest Gaussian the learner allows, sampled at its mean, is the densest honest case
    top = 2 * (-LOG_STD_MIN - 0.5 * math.log(2 * math.pi))
    assert _reason(_unroll(behaviour_logp=np.full(T, top, np.float32))) is None


@pytest.mark.parametrize("over, reason", [
    (dict(action=np.zeros(T, np.int64)), "action_range"),  # indices, for a Box env
    (dict(action=np.zeros((T, 3), np.float32)), "action_range"),  # another dimension
    (dict(action=np.full((T, 2), 2 * MAX_ABS_ACTION, np.float32)), "action_range"),
    (dict(behaviour_logp=np.full(T, 2 * (-LOG_STD_MIN) + 1, np.float32)), "logp_range"),
    (dict(behaviour_logp=np.full(T, -5000.0, np.float32)), "logp_range"),
    (dict(behaviour_logits=np.zeros((T, 2), np.float32)), "spec"),
], ids=["int actions", "wrong dimension", "absurd action", "logp above any density", "logp far below", "logits"])
def test_checks_refuse_what_a_gaussian_policy_cannot_send(over, reason):
    assert _reason(_unroll(**over)) == reason


def test_discrete_checks_refuse_continuous_actions():
    checker = UnrollChecker.from_spaces(OBS_SPACE, gym.spaces.Discrete(3), max_abs_reward=10.0)
    u = _unroll(behaviour_logp=np.full(T, -1.0, np.float32))
    assert _reason(u, checker) == "action_range"
    assert _reason(_unroll(action=np.array([0, 1, 2, 1, 0], np.int64), behaviour_logp=np.full(T, -1.0, np.float32)),
                   checker) is None


# -- A3C on continuous actions ------------------------------------------------------------------
def test_a3c_loss_of_a_gaussian_policy_by_hand():
    """``a3c_loss`` with a log std: the loss terms and their gradients w.r.t. the means, the log
    std and the values, written out (d logp / d mean = (a - mean) / sd^2, d logp / d log sd =
    z^2 - 1, dH / d log sd = 1 per dimension)."""
    from zenrl.common.a3c_loss import a3c_loss

    rng = np.random.default_rng(5)
    N, d, vc, ec = 6, 2, 0.5, 0.03
    mean = torch.tensor(rng.uniform(-0.9, 0.9, (N, d)), dtype=torch.float64, requires_grad=True)
    log_std = torch.tensor([-0.4, 0.3], dtype=torch.float64, requires_grad=True)
    values = torch.tensor(rng.normal(size=N), dtype=torch.float64, requires_grad=True)
    actions = rng.normal(scale=1.2, size=(N, d))
    returns = rng.normal(size=N)
    loss, m = a3c_loss(mean, values, torch.from_numpy(actions), torch.from_numpy(returns), vc, ec, log_std)
    loss.backward()
    mu, ls, v = mean.detach().numpy(), log_std.detach().numpy(), values.detach().numpy()
    sd = np.exp(ls)
    logp = np.array([_normal_logpdf(actions[i], mu[i], sd) for i in range(N)])
    adv = returns - v
    entropy = float(np.sum(ls + 0.5 + 0.5 * np.log(2 * np.pi)))
    assert m["policy_loss"] == pytest.approx(-np.mean(logp * adv), rel=1e-9)
    assert m["entropy"] == pytest.approx(entropy, rel=1e-9)
    assert m["value_loss"] == pytest.approx(np.mean(adv ** 2), rel=1e-9)
    assert float(loss.detach()) == pytest.approx(-np.mean(logp * adv) + vc * np.mean(adv ** 2) - ec * entropy, rel=1e-9)
    z = (actions - mu) / sd
    np.testing.assert_allclose(mean.grad.numpy(), -(adv / N)[:, None] * z / sd, rtol=1e-9)
    np.testing.assert_allclose(log_std.grad.numpy(), (-(adv / N)[:, None] * (z ** 2 - 1)).sum(0) - ec, rtol=1e-9)
    np.testing.assert_allclose(values.grad.numpy(), -2 * vc * adv / N, rtol=1e-9)


def test_a3c_rollout_of_continuous_actions_counts_env_steps():
    from zenrl.common.a3c_loss import Rollout, rollout_gradients

    net = _net(d=2)
    T_, E = 4, 3
    rng = np.random.default_rng(0)
    ro = Rollout(obs={"obs": rng.normal(size=(T_, E, 3)).astype(np.float32)},
                 actions=rng.normal(size=(T_, E, 2)).astype(np.float32), rewards=np.ones((T_, E), np.float32),
                 terminated=np.zeros((T_, E), bool), truncated=np.zeros((T_, E), bool),
                 final_obs={"obs": np.zeros((0, 3), np.float32)}, last_obs={"obs": np.zeros((E, 3), np.float32)})
    assert ro.steps == T_ * E
    grads, m = rollout_gradients(net, ro, 0.9, 0.5, 0.0)
    assert set(grads) == {k for k, _ in net.named_parameters()} and grads["log_std"].shape == (2,)
    assert all(np.isfinite(g).all() for g in grads.values()) and np.abs(grads["log_std"]).sum() > 0


# -- match opponents on a continuous action set -------------------------------------------------
@pytest.mark.parametrize("sets, refused", [
    (["selfplay.enabled=true"], "selfplay needs a discrete action set"),
    (["league.enabled=true"], "a league needs a discrete action set"),
    (["opponents.pool={me: {path: nowhere.pt}}"], "opponents.pool's frozen policies need"),
    (["opponents.pool={c: {bot: cheese}, w: {bot: waypoint}}"], None),
], ids=["selfplay", "league", "frozen policy", "bots"])
def test_frozen_opponents_need_a_discrete_action_set(sets, refused):
    """A frozen policy's action is an index of the match's action set: self-play, a league and
    frozen policies in the pool are refused at start on the continuous set, scripted bots play."""
    from zenrl.common.config import load_config
    from zenrl.common.errors import ConfigError
    from zenrl.common.opponents import check_opponents

    cfg = load_config(None, ["algo=impala", "env.id=zenrl/BurgerWar-v0", "env.kwargs={action_set: continuous}", *sets])
    env = make_env(cfg.env)
    try:
        assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        if refused is None:
            check_opponents(cfg, env)
        else:
            with pytest.raises(ConfigError, match=refused):
                check_opponents(cfg, env)
    finally:
        env.close()


def test_a_policy_opponent_on_a_continuous_action_set_is_refused_by_the_tools(tmp_path):
    from zenrl.common.errors import ConfigError, ZenrlError
    from zenrl.common.opponents import load_frozen
    from zenrl.tools.loading import load_player

    box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    with pytest.raises(ZenrlError, match="discrete action set"):
        load_player(tmp_path / "ckpt.pt", OBS_SPACE, box)
    with pytest.raises(ConfigError, match="opponents.pool.x: a frozen policy plays through a discrete action set"):
        load_frozen(tmp_path / "ckpt.pt", False, OBS_SPACE, box, "opponents.pool.x")
