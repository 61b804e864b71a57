"""The R2D2 actor (actor/r2d2.py) with an in-memory node, and greedy play of a recurrent network
carrying its state (the evaluator, the tools' GreedyPolicy, ``zenrl evaluate``).

The actor's sequences are checked end to end: the learner's loss with the acting network as
online and target network recomputes the priorities the actor sent, which holds only if every
stored state, observation, mask and bootstrap is the one the actor acted with (a state not zeroed
at an episode's start, or a policy state out of step with the builder, breaks it)."""

import numpy as np
import pytest
import torch

from tests.unit.actor_fakes import FakeNode, step_until, weights_payload
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.evaluator import Evaluator, build_policy_net
from zenrl.actor.r2d2 import R2D2Actor
from zenrl.common import protocol as P
from zenrl.common.config import RunConfig, load_config
from zenrl.common.env_factory import make_env
from zenrl.common.policy_io import GreedyPolicy
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.learner.r2d2_loss import r2d2_loss
from zenrl.replay.service import make_checker

E, M, BURN, N, H = 4, 8, 4, 3, 8
SCP = "zenrl/StatelessCartPole-v1"


def _cfg(tmp_path, *sets):
    return load_config(None, [f"runs_dir={tmp_path}", "algo=r2d2", f"env.id={SCP}", "env.max_episode_steps=12",
                              "network.hidden=[16]", f"actor.envs_per_actor={E}", "actor.chunk_size=16",
                              "actor.episode_report_s=0.01", f"r2d2.sequence_length={M}", f"r2d2.burn_in={BURN}",
                              f"r2d2.n_step={N}", f"r2d2.lstm_size={H}", "r2d2.block_steps=3", *sets], environ={})


def _sequences(node, actor_id="a0"):
    chunks = [P.TransitionBatch.decode(p) for p in node.sent(P.Keys("t").transitions(actor_id))]
    data = {k: np.concatenate([c.data[k] for c in chunks]) for k in chunks[0].data}
    return chunks, data, np.concatenate([c.priorities for c in chunks])


@pytest.mark.parametrize("torch_forward", [False, True])
def test_actor_sequences_pass_the_checks_and_the_loss_recomputes_their_priorities(tmp_path, torch_forward):
    cfg = _cfg(tmp_path)
    node = FakeNode(None)  # no learner: acts with the seeded initial weights
    actor = R2D2Actor(cfg, node, "t", "a0", slot=0, num_slots=2)
    if torch_forward:  # the route of conv encoders: RecurrentQNetwork.step instead of numpy
        actor.policy.q.fast = None
    assert (actor.policy.q.fast is None) == torch_forward
    with torch.no_grad():  # a sharper network than the initial one: states and Q values that matter
        for p in actor.net.parameters():
            p.mul_(3.0)
    actor.policy.sync()
    actor.start(node)
    for _ in range(150):
        assert actor.step(0.05)
    actor.close()  # flushes the sequences closed since the last block
    chunks, data, prio = _sequences(node)
    assert all(len(c.data["action"]) <= 2 for c in chunks)  # ceil(16 / 8) sequences per chunk
    assert len(prio) == actor.adder.values()["sent_sequences"] > 20
    assert actor.adder.values()["sent_transitions"] == int(data["mask"].sum())
    assert data["obs"].shape == (len(prio), M + 1, 2) and data["h"].shape == (len(prio), H)
    assert data["terminated"].any() and data["truncated"].any() and (~data["mask"]).any()
    # every sequence that starts its episode was acted on from the zero state, the others not
    first = data["first"]
    assert first.any() and (~first).any()
    assert not data["h"][first].any() and not data["c"][first].any()
    assert (np.abs(data["h"][~first]).sum(1) > 0).all()
    for c in chunks:
        assert make_checker(cfg).check(c.data, c.priorities) is None
    batch = {k: torch.from_numpy(v) for k, v in data.items()}
    batch["weights"] = torch.ones(len(prio))
    res = r2d2_loss(actor.net, actor.net, batch, burn_in=BURN, n_step=N, gamma=cfg.learner.gamma)
    np.testing.assert_allclose(res.priorities.numpy(), prio, rtol=1e-4, atol=1e-4)
    assert prio.max() > 0.1


def test_actor_takes_new_weights_and_stamps_its_chunks(tmp_path):
    cfg = _cfg(tmp_path)
    node = FakeNode(None)
    actor = R2D2Actor(cfg, node, "t", "a0", slot=0, num_slots=1)
    learner_net = build_policy_net(cfg, actor.envs)
    assert isinstance(learner_net, RecurrentQNetwork)
    with torch.no_grad():
        for p in learner_net.parameters():
            p.add_(1.0)
    actor.start(node)
    for _ in range(12):
        actor.step(0.05)
    node.latest.set("k", weights_payload(learner_net, version=7))
    for _ in range(40):
        actor.step(0.05)
    actor.close()
    assert actor.weights.version == 7
    assert all(torch.equal(a, b) for a, b in zip(actor.net.state_dict().values(), learner_net.state_dict().values()))
    versions = [P.TransitionBatch.decode(p).policy_version for p in node.sent(P.Keys("t").transitions("a0"))]
    assert versions[0] == -1 and versions[-1] == 7


# --------------------------------------------------------------------------------------------
# Greedy play carrying the state: the evaluator and the tools play the same episodes
# --------------------------------------------------------------------------------------------
def _eval_cfg(episodes):
    return RunConfig.model_validate({"algo": "r2d2", "env": {"id": SCP, "max_episode_steps": 60},
                                     "network": {"hidden": [16]}, "r2d2": {"lstm_size": H},
                                     "evaluator": {"episodes": episodes, "seed_offset": 0, "interval_s": 0.01}})


def _alternating_net(cfg):
    """A network whose greedy actions depend on its state alone: 1, 0, 1, 0, ... from an
    episode's start (LSTM unit 0 flips sign every step: input and output gates open, forget gate
    shut, cell input tanh(1 - 5 h); Q(1) - Q(0) = 2 h_0). Played without its state it always
    picks 1; played on from another episode's state it may start with 0."""
    envs = EnvBatch(cfg.env, 1, seed=0)
    net = build_policy_net(cfg, envs)
    envs.close()
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        lstm = net.lstm
        lstm.bias_ih_l0[0 * H] = 10.0      # input gate
        lstm.bias_ih_l0[1 * H] = -10.0     # forget gate
        lstm.bias_ih_l0[2 * H] = 1.0       # cell input
        lstm.weight_hh_l0[2 * H, 0] = -5.0
        lstm.bias_ih_l0[3 * H] = 10.0      # output gate
        net.advantage.weight[1, 0], net.advantage.weight[0, 0] = 1.0, -1.0
    return net


def _play(net, seeds, reset_every_step=False, reset_per_episode=True):
    """Each episode of ``seeds`` played with the tools' greedy policy; returns and first actions."""
    env = make_env(_eval_cfg(1).env)
    policy = GreedyPolicy(net, 2)
    rets, firsts = [], []
    for s in seeds:
        if reset_per_episode:
            policy.reset()
        obs, _ = env.reset(seed=s)
        ret, done, acts = 0.0, False, []
        while not done:
            if reset_every_step:
                policy.reset()
            acts.append(policy(obs))
            obs, r, term, trunc, _ = env.step(acts[-1])
            ret, done = ret + r, term or trunc
        rets.append(ret)
        firsts.append(acts[:4])
    env.close()
    return rets, firsts


def test_the_reference_policy_needs_its_state():
    net = _alternating_net(_eval_cfg(1))
    rets, firsts = _play(net, range(4))
    assert all(f == [1, 0, 1, 0] for f in firsts)
    assert _play(net, range(4), reset_every_step=True)[0] != rets      # always 1: falls over sooner
    assert _play(net, range(4), reset_per_episode=False)[0] != rets    # out of phase where an episode was odd


def test_the_state_follows_every_observation_also_under_random_actions():
    net = _alternating_net(_eval_cfg(1))
    obs = np.zeros(2, np.float32)
    policy = GreedyPolicy(net, 2, epsilon=1.0, seed=0)
    policy(obs)  # a random action; the state still took the step: the greedy one next is the second
    policy.epsilon = 0.0
    assert [policy(obs) for _ in range(3)] == [0, 1, 0]
    policy.reset()
    assert policy(obs) == 1


@pytest.mark.parametrize("use_numpy", [True, False])
def test_evaluator_rounds_equal_episodes_played_alone_with_the_state_carried(use_numpy):
    episodes = 3
    cfg = _eval_cfg(episodes)
    net = _alternating_net(cfg)
    node = FakeNode(weights_payload(net, version=1))
    ev = Evaluator(cfg, node, "t", use_numpy=use_numpy)
    assert (ev.policy.q.fast is not None) == use_numpy
    ev.start(node)
    results = []
    for v in (1, 2, 3):  # the same weights under new versions: a round each
        if v > 1:
            node.latest.set("k", weights_payload(net, version=v))
        step_until(ev, lambda: len(node.sent(P.Keys("t").eval)) == v)
        results.append(P.EvalResult.decode(node.sent(P.Keys("t").eval)[-1]).returns)
    ev.close()
    for k, rets in enumerate(results):  # round k plays seeds k * episodes + i
        np.testing.assert_array_equal(rets, _play(net, [k * episodes + i for i in range(episodes)])[0])


def test_zenrl_evaluate_plays_each_episode_from_a_zero_state_and_export_refuses_clearly(tmp_path):
    from zenrl.common.checkpoints import R2D2TrainingState
    from zenrl.common.networks import arch_fingerprint
    from zenrl.learner.checkpoint import save_checkpoint
    from zenrl.common.errors import ZenrlError
    from zenrl.tools import evaluate, export

    cfg = _eval_cfg(1)
    net = _alternating_net(cfg)
    state = R2D2TrainingState(arch=arch_fingerprint(net), version=1, config=cfg.model_dump(mode="json"),
                              learner={"online": net.state_dict(), "target": net.state_dict(), "optimizer": {},
                                       "updates": 3})
    path = save_checkpoint(tmp_path, state, keep=1)
    out = evaluate(str(path), episodes=4, seed=0, progress=False)
    assert [r["ret"] for r in out["results"]] == _play(net, range(4))[0]
    with pytest.raises(ZenrlError, match=r"recurrent \(r2d2\) policy cannot be exported yet"):
        export(str(path), str(tmp_path / "policy.pt"))
