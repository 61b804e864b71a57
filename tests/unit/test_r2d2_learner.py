"""The R2D2 learner (learner/r2d2.py): one step of its core against the loss, the guard and the
target network; resume bitwise; and the learner worker in process between a real replay service
and a real actor (sequences in, priorities back, weights out and loaded by the actor)."""

import numpy as np
import pytest
import torch

from tests.unit.actor_fakes import FakeNode, FakePub, wait_for
from zenrl.actor.r2d2 import R2D2Actor
from zenrl.common import protocol as P
from zenrl.common.checkpoints import R2D2TrainingState
from zenrl.common.config import load_config
from zenrl.common.roles import Supervisor
from zenrl.learner.checkpoint import read_checkpoint, save_checkpoint
from zenrl.learner.r2d2 import R2D2Core, R2D2Learner
from zenrl.learner.r2d2_loss import r2d2_loss
from zenrl.replay.service import ReplayService

E, M, BURN, N, H = 4, 8, 4, 3, 8


def _cfg(tmp_path, *sets):
    return load_config(None, [f"runs_dir={tmp_path}", "algo=r2d2", "env.id=zenrl/StatelessCartPole-v1",
                              "env.max_episode_steps=12", "network.hidden=[16]", f"actor.envs_per_actor={E}",
                              "actor.chunk_size=16", f"r2d2.sequence_length={M}", f"r2d2.burn_in={BURN}",
                              f"r2d2.n_step={N}", f"r2d2.lstm_size={H}", "r2d2.block_steps=3", "learner.batch_size=8",
                              "learner.lr=0.01", "learner.device=cpu", "replay.min_size=8", *sets], environ={})


def _actor_chunks(cfg, steps=120):
    """The chunks an R2D2 actor sends in ``steps`` batched steps (in memory)."""
    node = FakeNode(None)
    actor = R2D2Actor(cfg, node, "t", "a0", slot=0, num_slots=1)
    actor.start(node)
    for _ in range(steps):
        actor.step(0.05)
    actor.close()
    return node.sent(P.Keys("t").transitions("a0"))


def _batches(cfg, k, B=8):
    data = [P.TransitionBatch.decode(p).data for p in _actor_chunks(cfg)]
    data = {n: np.concatenate([d[n] for d in data]) for n in data[0]}
    rng = np.random.default_rng(0)
    out = []
    for _ in range(k):
        i = rng.choice(len(data["first"]), B, replace=False)
        out.append(({n: v[i] for n, v in data.items()}, rng.uniform(0.5, 1.0, B).astype(np.float32)))
    return out


def _core(cfg):
    torch.manual_seed(0)
    from zenrl.learner.base import env_facts

    spec, n, _ = env_facts(cfg)
    return R2D2Core(spec, n, cfg.network, cfg.learner, cfg.r2d2, torch.device("cpu"))


def _params(net):
    return [p.detach().clone() for p in net.parameters()]


def test_core_step_is_the_loss_with_priorities_target_copies_and_guard(tmp_path):
    cfg = _cfg(tmp_path, "learner.target_update_period=2")
    core = _core(cfg)
    (data, w), (data2, w2) = _batches(cfg, 2)
    b = core.batch_to_tensors(data, w)
    with torch.no_grad():
        want = r2d2_loss(core.online, core.target, b, burn_in=BURN, n_step=N, gamma=cfg.learner.gamma)
    before, target0 = _params(core.online), _params(core.target)
    m, prios = core.update(b)
    np.testing.assert_allclose(prios, want.priorities.numpy(), rtol=1e-6)
    assert m["loss"] == pytest.approx(float(want.loss)) and m["trained_steps"] == float(want.trained.sum())
    assert any(not torch.equal(a, b_) for a, b_ in zip(before, _params(core.online)))
    assert all(torch.equal(a, b_) for a, b_ in zip(target0, _params(core.target)))  # period 2: not yet
    core.update(core.batch_to_tensors(data2, w2))
    assert core.updates == 2 and all(torch.equal(a, b_) for a, b_ in zip(_params(core.online), _params(core.target)))
    # a batch with an action the network does not have is refused before the step
    bad = dict(data)
    bad["action"] = bad["action"].copy()
    bad["action"][0, -1] = 2
    with pytest.raises(ValueError, match="action 2 outside 0..1"):
        core.batch_to_tensors(bad, w)
    # a non-finite loss skips the update (the guard counts it)
    inf = dict(data)
    inf["reward"] = np.where(data["mask"], np.float32(3e38), 0).astype(np.float32)
    assert core.update(core.batch_to_tensors(inf, w)) == ({}, None)
    assert core.updates == 2 and core.guard.values()["skipped_updates"] == 1


def test_resume_next_update_is_bitwise_identical(tmp_path):
    cfg = _cfg(tmp_path, "learner.target_update_period=3")
    batches = _batches(cfg, 8)
    a = _core(cfg)
    for d, w in batches[:4]:
        a.update(a.batch_to_tensors(d, w))
    state = R2D2TrainingState(arch="x", version=1, config=cfg.model_dump(mode="json"), learner=a.state_dict(),
                              sequences_consumed=32)
    loaded = read_checkpoint(save_checkpoint(tmp_path, state, keep=1))
    assert isinstance(loaded, R2D2TrainingState) and loaded.sequences_consumed == 32 and loaded.updates == 4
    b = _core(cfg)
    b.load_state_dict(loaded.learner)
    for d, w in batches[4:]:  # crosses a target-network copy (period 3)
        ma, pa = a.update(a.batch_to_tensors(d, w))
        mb, pb = b.update(b.batch_to_tensors(d, w))
        assert ma == mb and np.array_equal(pa, pb)
    for va, vb in zip(a.online.state_dict().values(), b.online.state_dict().values()):
        assert torch.equal(va, vb)


class LoopbackNode:
    """The learner's side of the network with the replay service in this process: sample
    queries answered by it at once, priorities put straight into it, anything else recorded."""

    def __init__(self, svc: ReplayService) -> None:
        self.svc = svc
        self.pubs: dict[str, FakePub] = {}
        self.queryables: dict = {}

    def publisher(self, key, low_priority=False, express=False):
        pub = self.pubs.setdefault(key, FakePub())
        if key == self.svc.keys.priorities:
            pub.put = lambda payload: self.svc.sampler.on_priorities(key, payload)
        return pub

    def queryable(self, key, handler):
        self.queryables[key] = handler

    def query_async(self, key, payload, timeout_s, on_reply):
        assert key == self.svc.keys.sample
        on_reply(self.svc.sampler.on_sample(payload))

    def sent(self, key):
        return self.pubs[key].sent if key in self.pubs else []


def test_learner_worker_trains_on_the_replay_and_its_weights_load_into_an_actor(tmp_path):
    cfg = _cfg(tmp_path, "learner.publish_every_updates=5", "learner.send_linger_s=0")
    svc = ReplayService(cfg, None, "t")
    assert svc.ingest_many([(p, "k/a0") for p in _actor_chunks(cfg)]) > 8
    keys0, prios0 = svc.buffer.raw_priorities()
    node = LoopbackNode(svc)
    learner = R2D2Learner(cfg, node, "t")
    learner.start(node, Supervisor())
    try:
        while learner.updates < 20:
            assert learner.step(1.0)
        wait_for(lambda: learner._sender.sent >= 4, what="priorities and weights sent")
        vals, line = learner.report(1.0)
    finally:
        learner.close()
    assert vals["updates"] == 20 and vals["sequences_consumed"] == 20 * 8 and vals["sequences_per_s"] > 0
    assert vals["trained_steps_per_s"] > 0 and 1 <= vals["trained_steps_per_sequence"] <= M
    assert "transitions_per_s" not in vals and vals["skipped_updates"] == 0 and line.startswith("updates 20")
    # priorities came back: the replay's differ from the actor's initial ones
    keys1, prios1 = svc.buffer.raw_priorities()
    assert np.array_equal(keys0, keys1) and not np.allclose(prios0, prios1)
    # weights: the initial ones and every 5 updates; an actor of the run loads the newest
    weights = [P.Weights.decode(p) for p in node.sent(learner.keys.weights)]
    assert [w.updates for w in weights] == [0, 5, 10, 15, 20] and weights[-1].version == learner.version
    actor = R2D2Actor(cfg, FakeNode(None), "t", "a0", slot=0, num_slots=1)
    actor.node.latest.set("k", node.sent(learner.keys.weights)[-1])
    assert actor.weights.maybe_load() and actor.weights.version == learner.version
    for a, b in zip(actor.net.state_dict().values(), learner.dqn.online.state_dict().values()):
        assert torch.equal(a, b)


@pytest.mark.parametrize("sets, words", [
    (["r2d2.sequence_length=7"], "r2d2.sequence_length must be even"),
    (["r2d2.sequence_length=8", "r2d2.burn_in=5"], "r2d2.burn_in must be at most sequence_length / 2 = 4"),
    (["r2d2.lstm_size=0"], "r2d2.lstm_size"),
    (["r2d2.eta=1.5"], "r2d2.eta"),
    (["algo=r2d3"], "algo"),
])
def test_r2d2_options_are_validated_with_the_bad_value_named(sets, words):
    from zenrl.common.errors import ConfigError

    with pytest.raises(ConfigError, match=words):
        load_config(None, ["algo=r2d2", *sets], environ={})
    assert load_config(None, ["algo=r2d2", "r2d2.sequence_length=8", "r2d2.burn_in=4"], environ={}).r2d2.burn_in == 4
