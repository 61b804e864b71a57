"""Poison inside the bounds (issue #32, item 2): items whose in-bounds values make the learner's
loss or gradient non-finite are blamed one by one, left out of the step (the others are trained
on, their priorities computed as by hand), reported to the replay, which never samples them again
and charges their sender; a real CartPole observation at its velocity bound (float32's max) no
longer stalls the learner."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from zenrl.common import protocol as P
from zenrl.common.config import LearnerConfig, NetworkConfig, load_config
from zenrl.common.errors import ProtocolError
from zenrl.common.specs import ArraySpec
from zenrl.learner.dqn import DQNLearner
from zenrl.replay.buffer import InMemoryReplay
from zenrl.replay.checks import ChunkChecker
from zenrl.replay.service import ReplayService

F32_MAX = float(np.finfo(np.float32).max)

# the hand-made net and batch of test_dqn's step by hand: a 3-2-2 ReLU net, online != target
W1 = np.array([[0.5, -0.2, 0.1], [0.3, 0.4, -0.1]])
B1 = np.array([0.1, 0.2])
W2 = np.array([[1.0, -0.5], [0.2, 0.8]])
B2 = np.array([0.05, -0.05])
TARGET = (W1 * 0.5, B1 + 0.3, W2[::-1] * 2.0, B2 * -3.0)
OBS = np.array([[1.0, 0.5, 0.2], [0.4, 1.0, 0.3], [0.9, 0.1, 1.2]])
NXT = np.array([[0.8, 0.9, 0.1], [1.1, 0.2, 0.4], [0.3, 0.7, 0.9]])
ACTION = np.array([0, 1, 1])
REWARD = np.array([1.0, -0.5, 2.0])
N = np.array([3, 1, 2])
TERM = np.array([False, False, True])
ISW = np.array([1.0, 0.5, 0.25])
GAMMA, DELTA, CLIP, LR, EPS = 0.9, 1.0, 0.5, 0.01, 1e-3


def _forward(x, A1, a1, A2, a2):
    pre = x @ A1.T + a1
    h = np.maximum(pre, 0.0)
    return pre, h, h @ A2.T + a2


def _expected_step():
    """(|td| float[3], parameters after the step) of the three honest items, by hand."""
    _, _, q_next_on = _forward(NXT, W1, B1, W2, B2)
    _, _, q_next_tg = _forward(NXT, *TARGET)
    y = REWARD + GAMMA ** N * (1 - TERM) * q_next_tg[np.arange(3), q_next_on.argmax(1)]
    pre, h, q = _forward(OBS, W1, B1, W2, B2)
    err = q[np.arange(3), ACTION] - y
    dq = np.zeros_like(q)
    dq[np.arange(3), ACTION] = ISW * np.clip(err, -DELTA, DELTA) / 3  # the mean over the 3 kept
    dpre = (dq @ W2) * (pre > 0)
    grads = [dpre.T @ OBS, dpre.sum(0), dq.T @ h, dq.sum(0)]
    norm = np.sqrt(sum((g ** 2).sum() for g in grads))
    grads = [g * min(1.0, CLIP / (norm + 1e-6)) for g in grads]
    return np.abs(err), [p - LR * g / (np.abs(g) + EPS) for p, g in zip((W1, B1, W2, B2), grads)]


def _learner(max_priority=math.inf, max_abs_obs=math.inf):
    learner = DQNLearner({"obs": ArraySpec((3,), "float32")}, 2, NetworkConfig(hidden=[2], dueling=False),
                         LearnerConfig(lr=LR, adam_eps=EPS, gamma=GAMMA, huber_delta=DELTA, grad_clip=CLIP,
                                       target_update_period=1000, optimizer="adam", max_abs_obs=max_abs_obs),
                         torch.device("cpu"),
                         max_priority=max_priority)
    f32 = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        for net, (A1, a1, A2, a2) in ((learner.online, (W1, B1, W2, B2)), (learner.target, TARGET)):
            lin1, lin2 = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
            lin1.weight.copy_(f32(A1)), lin1.bias.copy_(f32(a1)), lin2.weight.copy_(f32(A2)), lin2.bias.copy_(f32(a2))
    return learner


def _batch_with(at, **poison):
    """The three honest items with a fourth inserted at index ``at`` (``poison``: its fields)."""
    row = {"obs": [0.5, 0.5, 0.5], "next_obs": [0.5, 0.5, 0.5], "action": 0, "reward": 0.0, "n": 1,
           "terminated": False, "w": 1.0, **poison}
    ins = lambda a, v, dt: np.insert(np.asarray(a, dt), at, np.asarray(v, dt), axis=0)  # noqa: E731
    data = {"obs": ins(OBS, [row["obs"]], np.float32), "next_obs": ins(NXT, [row["next_obs"]], np.float32),
            "action": ins(ACTION, row["action"], np.int64), "reward": ins(REWARD, row["reward"], np.float32),
            "n": ins(N, row["n"], np.uint8), "terminated": ins(TERM, row["terminated"], bool)}
    return data, ins(ISW, row["w"], np.float32)


def _check_step(learner, prios, metrics, at, repaired=1):
    td, expected = _expected_step()
    np.testing.assert_array_equal(learner.poisoned, [at])
    assert prios[at] == 0.0 and metrics["loss"] > 0 and learner.updates == 1
    assert learner.repaired_updates == repaired and learner.poisoned_total == 1
    np.testing.assert_allclose(np.delete(prios, at), td, rtol=1e-5)
    lin1, lin2 = [m for m in learner.online.modules() if isinstance(m, torch.nn.Linear)]
    for name, g, e in zip(("W1", "b1", "W2", "b2"), [lin1.weight, lin1.bias, lin2.weight, lin2.bias], expected):
        np.testing.assert_allclose(g.detach().numpy(), e, rtol=1e-5, atol=1e-7, err_msg=name)
    assert learner.guard.skipped == 0 and learner.guard.in_a_row == 0


@pytest.mark.parametrize("poison", [
    {"obs": [F32_MAX, 0.0, 0.0]},            # the forward overflows: Q(s) is inf (a second forward)
    {"next_obs": [0.0, -F32_MAX, F32_MAX]},  # finite but huge: |TD| > max_priority (the same forward)
    {"obs": [0.0, F32_MAX, -F32_MAX], "next_obs": [F32_MAX, F32_MAX, F32_MAX]},
])
def test_an_item_that_overflows_the_forward_is_blamed_and_the_others_stepped_as_by_hand(poison):
    learner = _learner(max_priority=1e6)  # no observation screen: blamed in the step
    metrics, prios = learner.update(learner.batch_to_tensors(*_batch_with(1, **poison)))
    _check_step(learner, prios, metrics, 1)
    # with the screen (learner.max_abs_obs), left out before the forward: the same step
    screened = _learner(max_priority=1e6, max_abs_obs=1e6)
    b = screened.batch_to_tensors(*_batch_with(1, **poison))
    assert b["obs"]["obs"].shape[0] == 3 and b["_screened"].tolist() == [1]
    metrics, prios = screened.update(b)
    _check_step(screened, prios, metrics, 1, repaired=0)


def test_an_item_whose_td_exceeds_max_priority_is_blamed_when_the_sum_overflows():
    """A finite reward near float32's max: each item's loss is finite, their sum is not; with a
    bound on |TD| the item is to blame, without one nobody is (the step is skipped)."""
    data, w = _batch_with(2, reward=3e38)
    data["reward"][0] = 3e38  # two of them: the sum overflows
    learner = _learner(max_priority=1e6)
    metrics, prios = learner.update(learner.batch_to_tensors(data, w))
    np.testing.assert_array_equal(learner.poisoned, [0, 2])
    assert learner.updates == 1 and (prios[[0, 2]] == 0).all() and (prios <= 1e6).all()
    unbounded = _learner()
    assert unbounded.update(unbounded.batch_to_tensors(data, w)) == ({}, None)
    assert unbounded.poisoned.size == 0 and unbounded.guard.skipped == 1


def test_an_item_with_a_finite_forward_but_an_overflowing_gradient_is_found_by_bisection():
    """obs 1e25 (without the observation screen): Q and the loss are finite (so no forward value
    blames it), but the gradient of the first layer's weights (obs times a bounded error)
    squares past float32's range."""
    learner = _learner()
    data, w = _batch_with(3, obs=[1e25, 1e25, 0.0], action=1)
    with torch.no_grad():
        t = learner.loss_terms(learner.batch_to_tensors(data, w))
        assert math.isfinite(t.loss.item()) and not t.bad().any()
    metrics, prios = learner.update(learner.batch_to_tensors(data, w))
    _check_step(learner, prios, metrics, 3)


def test_a_batch_that_is_all_poison_is_the_learners_problem_skipped_and_not_reported():
    learner = _learner(max_priority=1e6)
    data, w = _batch_with(0)
    data["obs"][:] = F32_MAX
    assert learner.update(learner.batch_to_tensors(data, w)) == ({}, None)
    assert learner.poisoned.size == 0 and learner.guard.skipped == 1 and learner.updates == 0


# -- the replay's side ------------------------------------------------------------------------------
B = 8


def _chunk(actor, seq, obs=None):
    rng = np.random.default_rng(seq)
    data = {"obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32), "action": rng.integers(0, 2, B),
            "reward": np.ones(B, np.float32), "next_obs": rng.uniform(-0.4, 0.4, (B, 4)).astype(np.float32),
            "terminated": np.zeros(B, bool), "truncated": np.zeros(B, bool), "n": np.ones(B, np.uint8)}
    if obs is not None:
        data["obs"][0] = obs
    return P.TransitionBatch(actor, 0, seq, data).encode()


def _service(*sets):
    cfg = load_config(None, ["replay.capacity=100", "replay.min_size=1", "replay.alpha=1.0",
                             "replay.quarantine_rejections=3", *sets], environ={})
    return ReplayService(cfg, node=None, run_id="r")


def test_the_replay_removes_poisoned_items_charges_their_sender_and_updates_the_others():
    svc = _service()
    keys = P.Keys("r")
    assert svc.ingest(_chunk("honest", 0), keys.transitions("honest")) == B
    assert svc.ingest(_chunk("evil", 1, obs=[0.0, F32_MAX, 0.0, 0.0]), keys.transitions("evil")) == B  # in bounds
    evil_key = B  # the evil chunk's first item
    upd = P.PriorityUpdate(keys=np.array([0, 1, 9], np.int64), priorities=np.array([0.5, 2.0, 3.0], np.float32),
                           poisoned=np.array([evil_key], np.int64))
    svc.sampler.on_priorities(keys.priorities, upd.encode())
    b = svc.buffer
    eps = b.eps
    np.testing.assert_allclose(b.priorities_of(np.array([0, 1, 9, evil_key])), [0.5 + eps, 2.0 + eps, 3.0 + eps, 0.0])
    v = svc.stats_values()
    assert v["poison_removed"] == 1 and v["rejected_poison"] == 1 and v["rejected_from/evil"] == 1
    assert "rejected_from/honest" not in v and v["quarantined"] == 0
    s = b.sample(256, 0.4, np.random.default_rng(0))
    assert evil_key not in s.keys
    # an in-flight priority for it does not bring it back; a second report is stale, not charged
    svc.sampler.on_priorities(keys.priorities, P.PriorityUpdate(keys=np.array([evil_key], np.int64),
                              priorities=np.array([9.0], np.float32), poisoned=np.array([evil_key], np.int64)).encode())
    assert b.priorities_of(np.array([evil_key]))[0] == 0.0
    v = svc.stats_values()
    assert v["poison_stale"] == 1 and v["rejected_poison"] == 1
    # a sender that keeps sending them is quarantined (3 rejections here)
    svc.sampler.on_priorities(keys.priorities, P.PriorityUpdate(
        keys=np.zeros(0, np.int64), priorities=np.zeros(0, np.float32),
        poisoned=np.array([evil_key + 1, evil_key + 2], np.int64)).encode())
    v = svc.stats_values()
    assert v["rejected_poison"] == 3 and v["quarantined"] == 1 and "evil" in v["quarantined_sources"]
    assert svc.ingest(_chunk("honest", 2), keys.transitions("honest")) == B


def test_poison_of_items_restored_from_the_log_is_charged_to_an_unknown_sender(tmp_path):
    sets = [f"runs_dir={tmp_path}", "replay.durable=true"]
    svc = _service(*sets)
    svc.ingest(_chunk("a", 0), "zenrl/r/transitions/a")
    svc.close()
    svc = _service(*sets)  # restored from its log: who sent what is not logged
    assert svc.restored_items == B
    svc.sampler.on_priorities("k", P.PriorityUpdate(keys=np.zeros(0, np.int64), priorities=np.zeros(0, np.float32),
                                                    poisoned=np.array([3], np.int64)).encode())
    v = svc.stats_values()
    assert v["poison_removed"] == 1 and v["rejected_from/(unknown)"] == 1 and "rejected_from/a" not in v
    svc.close()
    with pytest.raises(ProtocolError):  # a name no actor can have: never an actor's quarantine
        P.check_name("actor_id", "(unknown)")


@pytest.mark.parametrize("poisoned, reason", [
    (np.array([-1], np.int64), "negative"),
    (np.array([1.0], np.float32), "dtype"),
    (np.zeros((1, 1), np.int64), "shape"),
    (np.zeros(P.MAX_SAMPLE_BATCH + 1, np.int64), "size"),
])
def test_bad_poison_reports_are_rejected_by_reason_and_change_nothing(poisoned, reason):
    svc = _service()
    svc.ingest(_chunk("a", 0), "zenrl/r/transitions/a")
    env = {"v": P.PROTOCOL_VERSION, "t": "priorities", "keys": P.encode_array(np.array([1], np.int64)),
           "priorities": P.encode_array(np.array([5.0], np.float32)), "poisoned": P.encode_array(poisoned)}
    import msgpack

    payload = msgpack.packb(env, use_bin_type=True)
    with pytest.raises(ProtocolError) as e:
        P.PriorityUpdate.decode(payload)
    assert e.value.reason == reason
    svc.sampler.on_priorities("zenrl/r/replay/priorities", payload)
    v = svc.stats_values()
    assert v[f"rejected_{reason}"] == 1 and v["poison_removed"] == 0
    assert svc.buffer.priorities_of(np.array([1]))[0] == pytest.approx(1.0, rel=1e-5)  # untouched


def test_an_update_without_poisoned_keys_encodes_as_before():
    """Old peers see the same bytes: the optional field is left out when there is none."""
    upd = P.PriorityUpdate(keys=np.array([1], np.int64), priorities=np.array([0.5], np.float32))
    import msgpack

    assert "poisoned" not in msgpack.unpackb(upd.encode())
    assert P.PriorityUpdate.decode(upd.encode()).poisoned is None


# -- the real CartPole case -----------------------------------------------------------------------
def test_cartpole_at_its_velocity_bound_no_longer_stalls_the_learner():
    """Real CartPole transitions, 1% of them with a velocity of float32's max (inside the env's
    Box, so the replay's checks pass them): the learner keeps stepping, every such item is
    blamed and removed after it is first sampled, and no honest item is."""
    env = gym.make("CartPole-v1")
    checker = ChunkChecker.from_spaces(env.observation_space, env.action_space, 1, 1e3, 1e6)
    rng = np.random.default_rng(0)
    rows = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "n")}
    obs, _ = env.reset(seed=0)
    while len(rows["obs"]) < 2000:
        a = int(rng.integers(2))
        nxt, r, term, trunc, _ = env.step(a)
        for k, v in zip(rows, (obs, a, r, nxt, term, trunc, 1)):
            rows[k].append(v)
        obs = nxt if not (term or trunc) else env.reset()[0]
    env.close()
    dtypes = {"obs": np.float32, "action": np.int64, "reward": np.float32, "next_obs": np.float32,
              "terminated": bool, "truncated": bool, "n": np.uint8}
    data = {k: np.asarray(v, dtypes[k]) for k, v in rows.items()}
    bad = rng.choice(2000, 20, replace=False)
    data["obs"][bad[:10], 1] = F32_MAX    # cart velocity
    data["next_obs"][bad[10:], 3] = -F32_MAX  # pole angular velocity
    assert checker.check(data, None) is None, "the poison must be inside the env's bounds"

    cfg = load_config(None, ["learner.batch_size=64", "network.hidden=[32]"], environ={})
    torch.manual_seed(0)
    learner = DQNLearner({"obs": ArraySpec((4,), "float32")}, 2, cfg.network, cfg.learner, torch.device("cpu"),
                         max_priority=cfg.replay.max_priority)
    rb = InMemoryReplay({k: ArraySpec(v.shape[1:], v.dtype.name) for k, v in data.items()}, 4000, alpha=0.6, seed=0)
    keys = rb.insert(data)
    poison = set(keys[bad].tolist())
    removed: set[int] = set()
    for _ in range(300):
        s = rb.sample(64, 0.4, rng)
        _, prios = learner.update(learner.batch_to_tensors(s.data, s.weights))
        blamed = s.keys[learner.poisoned]
        rb.remove(blamed)
        removed.update(blamed.tolist())
        keep = np.ones(64, bool)
        keep[learner.poisoned] = False
        if prios is not None:
            rb.update_priorities(s.keys[keep], prios[keep])
        assert set(blamed.tolist()) <= poison  # never an honest item
    assert learner.updates == 300 and learner.guard.skipped == 0
    assert removed == poison and rb.removed_total == 20
    assert learner.params_finite()


# -- R2D2 -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("screen", [True, False])
def test_r2d2_blames_the_sequence_that_overflows_and_steps_on_the_others(tmp_path, screen):
    """One sequence of eight with a -float32-max observation inside its burn-in: left out by the
    observation screen, or (without it) blamed in the step, the recurrent state having carried
    the overflow to every later step; the step and the other sequences' priorities are those of
    the same core stepped on the other seven."""
    from tests.unit.test_r2d2_learner import _batches, _cfg, _core

    cfg = _cfg(tmp_path, *([] if screen else ["learner.max_abs_obs=1e39"]))
    (data, w), = _batches(cfg, 1)
    data = {k: v.copy() for k, v in data.items()}
    data["obs"][5, 1, :] = -F32_MAX  # (an LSTM saturates on many such values; not on this one)
    core, ref = _core(cfg), _core(cfg)
    core.max_priority = ref.max_priority = cfg.replay.max_priority
    m, prios = core.update(core.batch_to_tensors(data, w))
    np.testing.assert_array_equal(core.poisoned, [5])
    keep = np.delete(np.arange(8), 5)
    m_ref, p_ref = ref.update(ref.batch_to_tensors({k: v[keep] for k, v in data.items()}, w[keep]))
    np.testing.assert_allclose(prios[keep], p_ref, rtol=1e-6)
    assert prios[5] == 0 and m["loss"] == pytest.approx(m_ref["loss"], rel=1e-6)
    for a, b in zip(core.online.parameters(), ref.online.parameters()):
        torch.testing.assert_close(a, b)
    assert core.updates == 1 and core.guard.skipped == 0 and core.repaired_updates == (0 if screen else 1)


# -- IMPALA -----------------------------------------------------------------------------------------
def test_impala_leaves_out_the_unroll_that_overflows_charges_its_sender_and_steps_on_the_others(tmp_path):
    """Unrolls are consumed once, so a skipped batch never stalls IMPALA, but it used to cost the
    honest unrolls of the batch and charge nobody: now the poisoned unroll (inside CartPole's
    bounds) is found by bisection, charged as ``poison``, and the step is the one on the rest."""
    from tests.unit.test_impala import T, _cfg, _feed, _unroll
    from zenrl.learner.impala import ImpalaLearner

    def learner(batch):
        torch.manual_seed(0)
        svc = ImpalaLearner(_cfg(tmp_path, **{"impala.batch_unrolls": batch}), None, "t")
        svc.start_offline()
        return svc

    svc, ref = learner(4), learner(3)
    assert _feed(svc, 3, actor="honest") == ["queued"] * 3
    obs = np.zeros((T + 1, 4), np.float32)
    obs[2] = [0.0, -F32_MAX, 0.0, -F32_MAX]
    poison = _unroll("evil", svc.version, seq=0, seed=9, obs={"obs": obs})
    assert svc.on_unroll("zenrl/t/unrolls/evil", poison.encode()) == "queued"  # passes every check
    assert svc.step(0.01) and svc.updates == 1 and svc.guard.skipped == 0
    vals, _ = svc.report(1.0)
    assert vals["poisoned_unrolls"] == 1 and vals["rejected_poison"] == 1 and vals["rejected_from/evil"] == 1
    assert "rejected_from/honest" not in vals
    assert _feed(ref, 3, actor="honest") == ["queued"] * 3
    assert ref.step(0.01)
    for a, b in zip(svc.net.parameters(), ref.net.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
