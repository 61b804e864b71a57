"""IMPALA as an algorithm, without a network: the actor's published unrolls against the env steps
it took (terminations, truncations with their final observations, continuity, the behaviour
log-probabilities against the network's softmax), and the learner fed unrolls directly (it
updates and broadcasts, drops stale ones, counts bad ones by reason and source, quarantines a
repeat offender, skips a non-finite update), the sampling policy's log-probabilities, and a
checkpoint round trip with resume."""

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from tests.unit.actor_fakes import FakeNode, run_until, step_until, weights_payload
from zenrl.actor.impala import ImpalaActor
from zenrl.actor.policies import Sampling
from zenrl.common import protocol as P
from zenrl.common.checkpoints import ImpalaTrainingState
from zenrl.common.config import load_config
from zenrl.common.networks import ActorCritic
from zenrl.common.specs import ArraySpec
from zenrl.learner.impala import ImpalaLearner

SPEC = {"obs": ArraySpec((4,), "float32")}
E, T = 4, 20


def _cfg(tmp_path, **kw):
    sets = [f"runs_dir={tmp_path}", "algo=impala", "network.hidden=[16]", f"actor.envs_per_actor={E}",
            f"impala.unroll_length={T}", "impala.batch_unrolls=4", "env.max_episode_steps=15",
            "actor.episode_report_s=0.01", "learner.log_interval_s=0.05"] + [f"{k}={v}" for k, v in kw.items()]
    return load_config(None, sets, environ={})


def _net(cfg, seed=123):
    torch.manual_seed(seed)
    return ActorCritic(SPEC, 2, cfg.network)


# --------------------------------------------------------------------------------------------
# The sampling policy's behaviour log-probabilities
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("epsilon", [0.0, 0.3])
def test_sampling_logp_is_the_log_probability_of_the_action_drawn(tmp_path, epsilon):
    net = _net(_cfg(tmp_path))
    with torch.no_grad():  # make the policy far from uniform
        net.policy.weight.mul_(300.0)
    pol = Sampling(net, 2, np.random.default_rng(0), epsilon, use_numpy=True, with_logp=True)
    obs = {"obs": np.random.default_rng(1).normal(size=(2000, 4)).astype(np.float32)}
    a, logp = pol.act(obs)
    assert a.dtype == np.int64 and logp.dtype == np.float32 and logp.shape == (2000,)
    with torch.no_grad():
        probs = torch.softmax(net({"obs": torch.as_tensor(obs["obs"])})[0].double(), 1).numpy()
    mu = (1 - epsilon) * probs + epsilon / 2
    np.testing.assert_allclose(logp, np.log(mu[np.arange(2000), a]), rtol=1e-4, atol=1e-5)
    # the actions follow mu: the mean probability of action 1 matches the frequency drawn
    assert abs(float((a == 1).mean()) - float(mu[:, 1].mean())) < 0.05
    # without with_logp the A3C policy is unchanged: no extras
    assert Sampling(net, 2, np.random.default_rng(0)).act(obs)[1] is None


# --------------------------------------------------------------------------------------------
# The actor: unrolls == the env steps it took
# --------------------------------------------------------------------------------------------
def _record_steps(actor):
    """Every ``(obs, actions, logp, result)`` the adder is given, in order (copies)."""
    steps = []
    add = actor.adder.add

    def recording(obs, actions, extras, res):
        steps.append(({k: v.copy() for k, v in obs.items()}, actions.copy(), extras.copy(), res))
        return add(obs, actions, extras, res)

    actor.adder.add = recording
    return steps


def test_published_unrolls_are_exactly_the_env_steps(tmp_path):
    cfg = _cfg(tmp_path)
    net = _net(cfg)
    node = FakeNode(weights_payload(net, version=7))
    a = ImpalaActor(cfg, node, "t", "a0", 0)
    steps = _record_steps(a)
    key = P.Keys("t").unrolls("a0")
    run_until(lambda stop: a.run(stop, max_unrolls=3 * E), lambda: a.done() and len(node.sent(key)) == 3 * E,
              what="3 rounds of unrolls")
    sent = [P.Unroll.decode(p) for p in node.sent(key)]
    assert len(sent) == 3 * E and len(steps) >= 3 * T
    assert [u.seq for u in sent] == list(range(3 * E))
    cuts = terms = 0
    for r in range(3):
        for e in range(E):
            u = sent[r * E + e]
            rec = steps[r * T:(r + 1) * T]
            assert u.actor_id == "a0" and u.policy_version == 7 and u.steps == T
            np.testing.assert_array_equal(u.obs["obs"][:T], np.stack([o["obs"][e] for o, _, _, _ in rec]))
            np.testing.assert_array_equal(u.obs["obs"][T], rec[-1][3].obs["obs"][e])
            np.testing.assert_array_equal(u.action, [act[e] for _, act, _, _ in rec])
            np.testing.assert_array_equal(u.behaviour_logp, [lp[e] for _, _, lp, _ in rec])
            np.testing.assert_array_equal(u.reward, [res.rewards[e] for _, _, _, res in rec])
            np.testing.assert_array_equal(u.terminated, [res.terminated[e] for _, _, _, res in rec])
            np.testing.assert_array_equal(u.truncated, [res.truncated[e] for _, _, _, res in rec])
            cut = [t for t, (_, _, _, res) in enumerate(rec) if res.truncated[e] and not res.terminated[e]]
            if cut:
                np.testing.assert_array_equal(u.final_obs["obs"], np.stack([rec[t][3].next_obs["obs"][e] for t in cut]))
                # the final observation is not the reset one the unroll continues with
                assert all(not np.array_equal(u.final_obs["obs"][i], u.obs["obs"][t + 1]) for i, t in enumerate(cut))
            else:
                assert u.final_obs is None
            cuts += len(cut)
            terms += int(u.terminated.sum())
            if r:  # an env's unrolls continue one another
                np.testing.assert_array_equal(u.obs["obs"][0], sent[(r - 1) * E + e].obs["obs"][T])
            # the behaviour log-probabilities are those of the network acted with
            with torch.no_grad():
                logp = F.log_softmax(net({"obs": torch.as_tensor(np.array(u.obs["obs"][:T]))})[0], 1)
            np.testing.assert_allclose(u.behaviour_logp, logp[torch.arange(T), torch.as_tensor(np.array(u.action))].numpy(),
                                       rtol=1e-4, atol=1e-5)
    assert cuts > 0 and terms > 0, "the unrolls should hold truncations and terminations"
    stats = P.Stats.decode(node.sent(P.Keys("t").stats("actor", "a0"))[-1]).values
    assert stats["sent_unrolls"] == 3 * E and stats["env_steps"] >= 3 * T * E


def test_actor_waits_for_the_learners_first_weights_and_stamps_the_version(tmp_path):
    cfg = _cfg(tmp_path)
    net = _net(cfg)
    node = FakeNode(None)
    a = ImpalaActor(cfg, node, "t", "a0", 0)
    a.start(node)
    assert not a.step(0.05) and a.env_steps == 0
    node.latest.set("k", weights_payload(net, version=4))
    key = P.Keys("t").unrolls("a0")
    step_until(a, lambda: len(node.sent(key)) == E)
    step_until(a, lambda: a.steps == T + 5)
    node.latest.set("k", weights_payload(net, version=9))  # in the middle of the second unroll
    step_until(a, lambda: len(node.sent(key)) == 3 * E)
    assert a.weights.version == 9
    # an unroll carries the version it began with (the oldest policy in it)
    assert [P.Unroll.decode(p).policy_version for p in node.sent(key)] == [4] * 2 * E + [9] * E


def test_lz4_compresses_image_unrolls(tmp_path):
    from zenrl.actor.adders import UnrollsToLearner
    from zenrl.actor.batch_env import StepResult

    keys = P.Keys("t")
    node = FakeNode()
    sizes = {}
    for codec in (None, "lz4"):
        ad = UnrollsToLearner(keys, "a0", 2, lambda: 3, 1 << 26, codec)
        ad.start(node)
        img = {"obs": np.zeros((1, 84, 84, 1), np.uint8)}
        z = np.zeros(1, bool)
        for _ in range(2):
            ad.add(img, np.zeros(1, np.int64), np.zeros(1, np.float32),
                   StepResult(img, img, np.zeros(1, np.float32), z, z, [], [], []))
        sizes[codec] = ad.sent_bytes
    sent = node.sent(keys.unrolls("a0"))
    assert len(sent) == 2 and sizes["lz4"] < sizes[None] / 10
    np.testing.assert_array_equal(P.Unroll.decode(sent[1]).obs["obs"], np.zeros((3, 84, 84, 1), np.uint8))


# --------------------------------------------------------------------------------------------
# The learner, fed unrolls directly
# --------------------------------------------------------------------------------------------
def _unroll(actor="a0", version=1, seq=0, seed=0, trunc_at=(), term_at=(), **override):
    rng = np.random.default_rng(seed)
    term = np.zeros(T, bool)
    trunc = np.zeros(T, bool)
    term[list(term_at)] = True
    trunc[list(trunc_at)] = True
    K = int((trunc & ~term).sum())
    fields = dict(obs={"obs": rng.uniform(-0.2, 0.2, (T + 1, 4)).astype(np.float32)},
                  action=rng.integers(0, 2, T).astype(np.int64),
                  behaviour_logp=np.full(T, np.log(0.5), np.float32), reward=np.ones(T, np.float32),
                  terminated=term, truncated=trunc,
                  final_obs={"obs": rng.uniform(-0.2, 0.2, (K, 4)).astype(np.float32)} if K else None)
    fields.update(override)
    return P.Unroll(actor_id=actor, policy_version=version, seq=seq, **fields)


def _feed(svc, n, actor="a0", version=None, key=None, **kw):
    outs = []
    for i in range(n):
        u = _unroll(actor, svc.version if version is None else version, seq=i, seed=i, **kw)
        outs.append(svc.on_unroll(key or f"zenrl/t/unrolls/{actor}", u.encode()))
    return outs


def _params(net):
    return [p.detach().clone() for p in net.parameters()]


@pytest.mark.parametrize("clip_eps", [None, 0.2])
def test_learner_updates_on_batches_and_broadcasts(tmp_path, clip_eps):
    svc = ImpalaLearner(_cfg(tmp_path, **{"impala.clip_eps": "null" if clip_eps is None else clip_eps}), None, "t")
    assert svc.loss_params.clip_eps == clip_eps  # APPO's clipped objective, or IMPALA's
    svc.start_offline()
    assert svc.version == 1
    assert _feed(svc, 3, trunc_at=(5,), term_at=(9,)) == ["queued"] * 3
    before = _params(svc.net)
    assert not svc.step(0.01) and svc.updates == 0  # 3 < B = 4 unrolls
    assert _feed(svc, 5, actor="a1") == ["queued"] * 5
    assert svc.step(0.01) and svc.updates == 1 and svc.version == 2
    assert any(not torch.equal(a, b) for a, b in zip(before, svc.net.parameters()))
    assert svc.env_steps_trained == 4 * T and len(svc.queue) == 4
    w = P.Weights.decode(svc._latest_weights)
    assert w.version == 2 and w.updates == 1
    vals, line = svc.report(1.0)
    assert vals["updates"] == 1 and vals["env_steps_trained"] == 4 * T and vals["rejected_total"] == 0
    assert {"loss", "policy_loss", "value_loss", "entropy", "rho_mean", "rho_max", "grad_norm", "queue_len",
            "queue_evicted", "stale_dropped", "policy_lag", "env_steps_per_s", "updates_per_s"} <= set(vals)
    assert vals["queue_taken"] == 4 and line and "updates 1" in line


def test_learner_drops_stale_unrolls(tmp_path):
    svc = ImpalaLearner(_cfg(tmp_path, **{"impala.max_policy_lag": 2}), None, "t")
    svc.start_offline()
    _feed(svc, 4)
    for _ in range(3):  # versions 1 -> 4 (the queue is refilled with current ones)
        assert svc.step(0.01)
        _feed(svc, 4)
    assert svc.version == 4
    assert _feed(svc, 2, version=1) == ["stale", "stale"]  # 4 - 1 = 3 > 2
    assert _feed(svc, 1, version=2) == ["queued"]           # 4 - 2 = 2, still taken
    assert svc.report(1.0)[0]["stale_dropped"] == 2


def test_learner_counts_bad_unrolls_by_reason_and_source_and_quarantines(tmp_path):
    cfg = _cfg(tmp_path, **{"impala.quarantine_rejections": 3})
    svc = ImpalaLearner(cfg, None, "t")
    svc.start_offline()
    good_before = _feed(svc, 1, actor="honest")
    bad = {"action_range": dict(action=np.full(T, 5, np.int64)),
           "reward_bound": dict(reward=np.full(T, 1e9, np.float32)),
           "obs_bounds": dict(obs={"obs": np.full((T + 1, 4), 1e6, np.float32)})}
    for reason, override in bad.items():
        assert _feed(svc, 1, actor="liar", **override) == ["rejected"]
        assert svc.rejects.counts[reason] == 1, reason
    assert svc.on_unroll("zenrl/t/unrolls/liar", b"\x00garbage") == "quarantined"  # the third one quarantined it
    assert svc.on_unroll("zenrl/t/unrolls/other", b"\x00garbage") == "rejected"
    # an unroll whose actor_id is not the key's sender
    assert _feed(svc, 1, actor="honest", key="zenrl/t/unrolls/impostor") == ["rejected"]
    vals, _ = svc.report(1.0)
    assert vals["rejected_total"] == 5 and vals["rejected_malformed"] == 1 and vals["rejected_source"] == 1
    assert vals["rejected_from/liar"] == 3 and vals["rejected_from/other"] == 1
    assert vals["quarantined"] == 1 and "liar" in vals["quarantined_sources"] and vals["dropped_quarantined"] == 1
    assert good_before == ["queued"] and svc.queue.sizes() == {"honest": 1}
    assert _feed(svc, 1, actor="honest") == ["queued"]  # the honest actor is not affected


def test_learner_skips_a_non_finite_update(tmp_path):
    svc = ImpalaLearner(_cfg(tmp_path), None, "t")
    svc.start_offline()
    before = _params(svc.net)
    with torch.no_grad():
        svc.net.value.bias.fill_(float("inf"))  # the loss becomes non-finite
    _feed(svc, 4)
    assert not svc.step(0.01) and svc.updates == 0 and svc.guard.skipped == 1
    with torch.no_grad():
        svc.net.value.bias.copy_(before[-1])
    assert all(torch.equal(a, b) for a, b in zip(before, svc.net.parameters()))
    assert svc.version == 1


def test_checkpoint_round_trip_and_resume(tmp_path):
    cfg = _cfg(tmp_path)
    svc = ImpalaLearner(cfg, None, "ck")
    svc.start_offline()
    _feed(svc, 8)
    assert svc.step(0.01) and svc.step(0.01)
    path = svc.save()
    again = ImpalaLearner(cfg, None, "ck", resume="require")
    st = again.training_state()
    assert isinstance(st, ImpalaTrainingState) and st.updates == 2 and st.env_steps_trained == 2 * 4 * T
    assert again.version >= svc.version and path.name == "ckpt-000000000002.pt"
    assert all(torch.equal(a, b) for a, b in zip(svc.net.parameters(), again.net.parameters()))
    # the same next batch gives the same parameters (the optimizer state came back too)
    for s in (svc, again):
        s.queue.set_version(0)
        _feed(s, 4, version=0)
        assert s.step(0.01)
    assert all(torch.equal(a, b) for a, b in zip(svc.net.parameters(), again.net.parameters()))


def test_actor_keeps_actor_max_steps_per_s(tmp_path):
    """actor.max_steps_per_s paces an IMPALA actor (it once applied to Ape-X and R2D2 actors only)."""
    cfg = _cfg(tmp_path, **{"actor.max_steps_per_s": 40})
    a = ImpalaActor(cfg, FakeNode(weights_payload(_net(cfg), version=1)), "t", "a0", 0)
    assert a.pacer is not None and a.pacer.period_s == pytest.approx(E / 40)
