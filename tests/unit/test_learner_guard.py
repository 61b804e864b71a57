"""The learner never trusts a batch: non-finite loss or gradient skips the update, K in a row
roll back, non-finite parameters are never checkpointed or published; actors refuse weights
that would load as non-finite."""

import logging

import numpy as np
import pytest
import torch

from tests.unit.test_dqn import _FakeNode, _learner_and_batch, _weights
from zenrl.actor.weights import WeightsFollower
from zenrl.common import protocol as P
from zenrl.common.config import NetworkConfig, load_config
from zenrl.common.networks import QNetwork
from zenrl.common.specs import ArraySpec
from zenrl.learner.guard import UpdateGuard, params_finite


def _params(net):
    return [p.detach().clone() for p in net.parameters()]


def _same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b))


def test_huge_reward_skips_the_update_and_leaves_the_network_alone():
    dqn, b = _learner_and_batch()
    before = _params(dqn.online)
    bad = dict(b, reward=b["reward"].clone())
    bad["reward"][:2] = 3e38  # finite, but their loss terms sum to inf
    m, prios = dqn.update(bad)
    assert prios is None and m == {} and dqn.updates == 0 and dqn.guard.skipped == 1
    assert _same(before, _params(dqn.online)) and dqn.params_finite()
    assert all(p.grad is None for p in dqn.online.parameters())
    # a good batch afterwards steps normally and resets the run of skips
    m, prios = dqn.update(b)
    assert prios is not None and np.isfinite(prios).all() and dqn.updates == 1 and dqn.guard.in_a_row == 0
    assert not _same(before, _params(dqn.online))


def test_out_of_range_action_is_refused_before_the_step():
    dqn, _ = _learner_and_batch()
    B = 4
    data = {"obs": np.zeros((B, 4), np.float32), "next_obs": np.zeros((B, 4), np.float32),
            "action": np.array([0, 1, 7, 0]), "reward": np.zeros(B, np.float32), "n": np.ones(B, np.uint8),
            "terminated": np.zeros(B, bool)}
    with pytest.raises(ValueError, match="action 7 outside 0..1"):
        dqn.batch_to_tensors(data, np.ones(B, np.float32))


def test_guard_counts_logs_once_per_interval_and_asks_for_rollback(caplog):
    now = [0.0]
    g = UpdateGuard(max_bad=3, log_interval_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="zenrl.learner.guard"):
        assert g.accept(1.0, 2.0)
        assert not g.accept(float("inf"), 1.0) and not g.accept(1.0, float("nan"))
        assert not g.rollback_due
        assert g.accept(0.5, 0.5) and g.in_a_row == 0  # a good update breaks the run
        for _ in range(3):
            assert not g.accept(float("nan"), float("nan"))
        assert g.rollback_due and g.skipped == 5
        now[0] = 11.0
        assert not g.accept(float("inf"), 0.0)
    assert len([r for r in caplog.records if "skipped" in r.message]) == 2  # at 0 s and at 11 s
    g.rolled_back()
    assert not g.rollback_due and g.values() == {"skipped_updates": 6, "rollbacks": 1, "params_unpublishable": 0}


def test_service_never_saves_or_publishes_nonfinite_params_and_rolls_back(tmp_path):
    from zenrl.learner.apex import ApexLearner

    cfg = load_config(None, [f"runs_dir={tmp_path}", "network.hidden=[8]", "learner.guard_max_bad_updates=2"])
    svc = ApexLearner(cfg, node=None, run_id="g")
    assert svc.save() is not None
    good = _params(svc.dqn.online)
    with torch.no_grad():
        next(svc.dqn.online.parameters())[0] = float("nan")
    assert not params_finite(svc.dqn.online.parameters())
    assert svc._publishable_weights() is None          # not broadcast ...
    assert _same(good, _params(svc.dqn.online))        # ... and rolled back to the checkpoint
    with torch.no_grad():
        next(svc.dqn.target.parameters())[0] = float("inf")
    n_ckpt = len(list((tmp_path / "g" / "checkpoints").glob("ckpt-*.pt")))
    assert svc.save() is None                          # not checkpointed either
    assert len(list((tmp_path / "g" / "checkpoints").glob("ckpt-*.pt"))) == n_ckpt
    assert svc.dqn.params_finite() and svc.dqn.guard.values()["params_unpublishable"] == 2
    assert svc.dqn.guard.rollbacks == 2
    w = P.Weights.decode(svc._publishable_weights())
    assert all(np.isfinite(a).all() for a in w.params.values())


def test_actor_refuses_weights_that_would_load_as_inf():
    spec = {"obs": ArraySpec((4,), "float32")}
    torch.manual_seed(0)
    learner_net = QNetwork(spec, 2, NetworkConfig(hidden=[16]))
    actor_net = QNetwork(spec, 2, NetworkConfig(hidden=[16]))
    before = _params(actor_net)
    node = _FakeNode()
    f = WeightsFollower(node, P.Keys("r"), actor_net, P.DEFAULT_MAX_MESSAGE_BYTES)
    w = P.Weights.decode(_weights(learner_net, 5))
    k0 = next(iter(w.params))
    params = {k: v.astype(np.float64) for k, v in w.params.items()}
    params[k0] = params[k0].copy()
    params[k0].flat[0] = 1e300  # finite as float64: passes the wire's NaN/Inf check
    node.latest = P.Weights(version=5, learner_id="l", arch=w.arch, updates=1, params=params).encode()
    assert not f.maybe_load() and f.rejected == 1 and f.version == -1
    assert _same(before, _params(actor_net))
    node.latest = _weights(learner_net, 6)  # good weights still load
    assert f.maybe_load() and f.version == 6


def test_k_skipped_updates_in_a_row_roll_back_to_the_last_checkpoint(tmp_path):
    from zenrl.learner.apex import ApexLearner

    cfg = load_config(None, [f"runs_dir={tmp_path}", "network.hidden=[8]", "learner.guard_max_bad_updates=3",
                             "learner.lr=0.01"])
    svc = ApexLearner(cfg, node=None, run_id="k")
    rng = np.random.default_rng(0)
    B = 16
    data = {"obs": rng.uniform(-0.1, 0.1, (B, 4)).astype(np.float32),
            "next_obs": rng.uniform(-0.1, 0.1, (B, 4)).astype(np.float32),
            "action": rng.integers(0, 2, B), "reward": np.ones(B, np.float32), "n": np.ones(B, np.uint8),
            "terminated": np.zeros(B, bool)}
    good = svc.dqn.batch_to_tensors(data, np.ones(B, np.float32))
    for _ in range(3):
        svc.dqn.update(good)
    svc.save()
    saved, saved_updates = _params(svc.dqn.online), svc.dqn.updates
    for _ in range(2):
        svc.dqn.update(good)  # moves on past the checkpoint
    assert not _same(saved, _params(svc.dqn.online))
    data["reward"][:] = 3e38  # every item to blame: the learner's problem, not the batch's
    bad = svc.dqn.batch_to_tensors(data, np.ones(B, np.float32))
    for i in range(3):
        assert svc.dqn.update(bad)[1] is None
        assert svc.dqn.guard.rollback_due == (i == 2)
    svc.rollback()
    assert _same(saved, _params(svc.dqn.online)) and svc.dqn.updates == saved_updates
    assert not svc.dqn.guard.rollback_due and svc.dqn.guard.rollbacks == 1
