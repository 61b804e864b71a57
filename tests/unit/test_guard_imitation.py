"""``learner.guard_imitation``: the match env's guard rule on a batch of detector readings
(worked out by hand), DQfD's large-margin loss against a by-hand reference, a learner step whose
loss adds it on the states where the rule fires, the network learning the guard's turns from it,
and the config errors where there is no guard to learn."""

import math
from typing import Dict

import numpy as np
import pytest
import torch

from zenrl.common.config import EnvConfig, LearnerConfig, NetworkConfig, RunConfig
from zenrl.common.errors import ConfigError
from zenrl.common.guard_rule import GuardRule
from zenrl.common.specs import ArraySpec
from zenrl.learner.base import env_facts
from zenrl.learner.dqn import DQNLearner, large_margin_losses

COS15 = math.cos(math.radians(15.0))
RULE = GuardRule(1.2, COS15, left=8, right=9)   # the rich action set's fastest turns on the spot


def test_rule_on_a_batch_of_readings():
    seen = np.array([
        [1.0, 0.5, 0.05],    # ahead, 5.7 deg off: no
        [1.0, 0.0, 0.5],     # 90 deg left
        [1.0, 0.0, -0.5],    # 90 deg right
        [1.0, -0.5, 0.0],    # straight behind: y = 0 turns right
        [1.0, 0.5, 0.2],     # 21.8 deg left, 0.54 m
        [1.0, 0.0, 1.3],     # beyond 1.2 m
        [0.0, 0.0, 0.5],     # not seen
        [1.0, 0.0, 0.0],     # on top of us: no bearing
        [1.0, np.nan, 0.5],  # a broken reading never fires
        [1.0, 1.0, 0.26],    # 14.6 deg: inside 15
        [1.0, 1.0, 0.27],    # 15.1 deg: outside
    ], np.float32)
    np.testing.assert_array_equal(RULE.actions(seen), [-1, 8, 9, 9, 8, -1, -1, -1, -1, -1, 8])
    np.testing.assert_array_equal(RULE.off_facing(seen), RULE.actions(seen) >= 0)
    assert RULE.actions(seen).dtype == np.int64
    with pytest.raises(ValueError, match="radius > 0"):
        GuardRule(0.0, COS15, 8, 9)


def test_env_rule_is_the_one_guard_action_reads(make_bw):
    env = make_bw(opponents="idle", enemy_detector=True, action_set="rich", face_radius=0.8, face_angle=30)
    rule = env.guard_rule()
    assert (rule.radius, rule.left, rule.right) == (0.8, 8, 9)
    assert rule.cos_angle == pytest.approx(math.cos(math.radians(30)))
    rng = np.random.default_rng(0)
    seen = np.concatenate([rng.integers(0, 2, (200, 1)), rng.uniform(-1.0, 1.0, (200, 2))], 1).astype(np.float32)
    assert [env.guard_action(s) for s in seen] == rule.actions(seen).tolist()
    assert (rule.actions(seen) >= 0).sum() > 20  # the sample exercises the rule
    with pytest.raises(ValueError, match="discrete action set"):
        make_bw(opponents="idle", enemy_detector=True, action_set="continuous").guard_rule()


class _NoAction(torch.nn.Module):
    def forward(self, obs: Dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.tensor(-1, dtype=torch.int64)


def test_the_exported_guard_is_the_same_rule():
    """The TorchScript export cannot call Python: ``_Guarded.forward`` keeps its own copy of the
    rule. On 400 readings (a quarter on the boundaries) it acts where GuardRule fires, with the
    same turn, and passes to the inner policy (here: -1) where it does not."""
    from zenrl.tools.torchscript import _Guarded

    rule = GuardRule(1.0, math.cos(math.radians(30.0)), left=8, right=9)
    guarded = torch.jit.script(_Guarded(_NoAction(), 1.0, 30.0, 8, 9).eval())
    rng = np.random.default_rng(1)
    r, a = rng.uniform(0.0, 1.4, 400), rng.uniform(-math.pi, math.pi, 400)
    r[:50], a[50:100] = 1.0 + rng.uniform(-1e-3, 1e-3, 50), np.radians(30.0) * rng.choice([-1, 1], 50) + rng.uniform(-1e-3, 1e-3, 50)
    seen = np.stack([rng.integers(0, 2, 400) | (np.arange(400) < 100), r * np.cos(a), r * np.sin(a)], 1).astype(np.float32)
    want = rule.actions(seen)
    got = [int(guarded({"enemy_seen": torch.from_numpy(s)})) for s in seen]
    assert got == want.tolist()
    assert 50 < (want >= 0).sum() < 350  # both outcomes, on and near the boundaries


def test_large_margin_loss_by_hand():
    q = torch.tensor([[1.0, 2.0, 0.5],
                      [1.0, 2.0, 0.5],
                      [3.0, 0.0, 2.5],
                      [0.0, 0.0, 0.0]], requires_grad=True)
    expert = torch.tensor([0, 1, 0, -1])
    j = large_margin_losses(q, expert, margin=0.8)
    # row 0: max(1 + 0, 2 + .8, .5 + .8) - 1 = 1.8; row 1: max(1.8, 2, 1.3) - 2 = 0;
    # row 2: max(3, .8, 3.3) - 3 = 0.3 (the margin, not the Q value, decides); row 3: no expert
    torch.testing.assert_close(j, torch.tensor([1.8, 0.0, 0.3, 0.0]))
    j.sum().backward()
    # the gradient raises the expert's Q and lowers the action that beat it by the margin
    torch.testing.assert_close(q.grad, torch.tensor([[-1.0, 1.0, 0.0], [0.0, 0.0, 0.0],
                                                     [-1.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))


SPEC = {"obs/enemy_seen": ArraySpec((3,), "float32"), "obs/lidar": ArraySpec((4,), "float32")}


def _batch(rng, n):
    seen = np.concatenate([np.ones((n, 1)), rng.uniform(-1.0, 1.0, (n, 2))], 1).astype(np.float32)
    lidar = rng.uniform(0.0, 1.0, (n, 4)).astype(np.float32)
    return {"obs/enemy_seen": seen, "obs/lidar": lidar, "next_obs/enemy_seen": seen, "next_obs/lidar": lidar,
            "action": rng.integers(0, 10, n).astype(np.int64), "reward": np.zeros(n, np.float32),
            "n": np.ones(n, np.uint8), "terminated": np.ones(n, bool)}


def _learner(weight, **kw):
    torch.manual_seed(0)
    cfg = LearnerConfig(lr=3e-3, guard_imitation=weight, guard_margin=0.8, **kw)
    return DQNLearner(SPEC, 10, NetworkConfig(hidden=[32], dueling=False), cfg, torch.device("cpu"),
                      guard=RULE if weight else None)


def test_the_step_adds_the_weighted_margin_on_the_states_where_the_rule_fires():
    rng = np.random.default_rng(1)
    data = _batch(rng, 64)
    w = rng.uniform(0.2, 1.0, 64).astype(np.float32)
    dqn = _learner(0.5)
    b = dqn.batch_to_tensors(data, w)
    g = RULE.actions(data["obs/enemy_seen"])
    np.testing.assert_array_equal(b["guard_action"].numpy(), g)
    assert 0 < (g >= 0).sum() < 64
    with torch.no_grad():
        q = dqn.online(b["obs"]).numpy().astype(np.float64)
    # by hand: terminal one-step items with reward 0, so the TD target is 0
    q_sa = q[np.arange(64), data["action"]]
    huber = np.where(np.abs(q_sa) <= 1.0, 0.5 * q_sa ** 2, np.abs(q_sa) - 0.5)
    margin = np.zeros(64)
    for i in np.flatnonzero(g >= 0):
        margin[i] = max(q[i, a] + (0.0 if a == g[i] else 0.8) for a in range(10)) - q[i, g[i]]
    expected = np.mean(w * huber + 0.5 * margin)
    metrics, prios = dqn.update(b)
    assert metrics["loss"] == pytest.approx(expected, rel=1e-5)
    assert metrics["guard_fired"] == pytest.approx((g >= 0).mean())
    assert metrics["guard_margin_loss"] == pytest.approx(margin[g >= 0].mean(), rel=1e-5)
    np.testing.assert_allclose(prios, np.abs(q_sa), rtol=1e-5)  # priorities stay the TD errors
    assert "guard_action" not in _learner(0.0).batch_to_tensors(data, w)


def test_the_network_learns_the_guards_turns():
    rng = np.random.default_rng(2)
    dqn, plain = _learner(1.0), _learner(0.0)
    for _ in range(150):
        data = _batch(rng, 64)
        w = np.ones(64, np.float32)
        dqn.update(dqn.batch_to_tensors(data, w))
        plain.update(plain.batch_to_tensors(data, w))
    test = _batch(np.random.default_rng(3), 500)
    g = RULE.actions(test["obs/enemy_seen"])
    fired = g >= 0
    with torch.no_grad():
        obs = {k: torch.from_numpy(test[k]) for k in SPEC}
        greedy, greedy_plain = dqn.online(obs).argmax(1).numpy(), plain.online(obs).argmax(1).numpy()
    assert fired.sum() > 100
    assert (greedy[fired] == g[fired]).mean() > 0.95
    assert (greedy_plain[fired] == g[fired]).mean() < 0.5  # without it, nothing teaches the turns


def test_no_guard_to_learn_is_a_config_error():
    with pytest.raises(ConfigError, match="enemy_detector"):
        DQNLearner({"obs": ArraySpec((4,), "float32")}, 2, NetworkConfig(hidden=[8]), LearnerConfig(guard_imitation=1.0),
                   torch.device("cpu"), guard=RULE)
    with pytest.raises(ConfigError, match="match env"):
        env_facts(RunConfig(env=EnvConfig(id="CartPole-v1"), learner=LearnerConfig(guard_imitation=1.0)))
    match = EnvConfig(id="zenrl/BurgerWar-v0", kwargs={"enemy_detector": True, "action_set": "users", "opponents": "idle",
                                                        "face_radius": 1.0, "face_angle": 30.0})
    spec, n, rule = env_facts(RunConfig(env=match, learner=LearnerConfig(guard_imitation=1.0)))
    assert "obs/enemy_seen" in spec and n == 5
    assert (rule.left, rule.right) == (3, 4)
    assert rule.radius == 1.0 and rule.cos_angle == pytest.approx(math.cos(math.radians(30.0)))
    assert env_facts(RunConfig(env=match))[2] is None  # off: no rule asked for
    with pytest.raises(ValueError, match="learner.guard_imitation is for algo apex"):
        RunConfig(algo="r2d2", learner=LearnerConfig(guard_imitation=1.0))
