"""The actor worker (actor/worker.py) in RoleLoop with an in-memory node: supervision of its
steps, and what the Ape-X and evaluation compositions publish (A3C's: tests/unit/test_a3c.py)."""

import math
import time

import numpy as np
import pytest
import torch

from tests.unit.actor_fakes import FakeNode, run_until, running, wait_for, weights_payload
from zenrl.actor.evaluator import Evaluator
from zenrl.actor.service import ApexActor
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.exploration import env_epsilons
from zenrl.common.networks import QNetwork
from zenrl.common.specs import ArraySpec

E, N_STEP = 4, 3


def _cfg(tmp_path, *sets):
    return load_config(None, [f"runs_dir={tmp_path}", "network.hidden=[16]", f"actor.envs_per_actor={E}",
                              f"actor.n_step={N_STEP}", "actor.chunk_size=8", "actor.episode_report_s=0.01",
                              "env.max_episode_steps=15", *sets], environ={})


def _stats(node, keys, role, ident):
    return [P.Stats.decode(p).values for p in node.sent(keys.stats(role, ident))]


def test_apex_actor_survives_a_failing_env_step_counts_it_and_publishes(tmp_path):
    cfg = _cfg(tmp_path)
    keys = P.Keys("t")
    node = FakeNode(None)  # no learner: acts with the seeded initial weights
    actor = ApexActor(cfg, node, "t", "a0", slot=1, num_slots=2)
    calls = [0]
    env_step = actor.envs.step

    def flaky(actions):
        calls[0] += 1
        if calls[0] == 5:
            raise RuntimeError("the simulator hiccuped")
        return env_step(actions)

    actor.envs.step = flaky
    steps = 40
    run_until(lambda stop: actor.run(stop, max_steps=steps),
              lambda: any(s["env_steps"] == steps * E and s["errors_total"] == 1 for s in _stats(node, keys, "actor", "a0")),
              what="the budget's stats")
    assert calls[0] == steps + 1, "the failing step must not end the actor, nor count as a step"
    last = _stats(node, keys, "actor", "a0")[-1]
    assert last["errors/RuntimeError"] == 1 and last["stalled"] == ""
    assert {k for k in last if not k.startswith("errors")} == {
        "env_steps", "slot", "policy_version", "sent_transitions", "sent_chunks", "failed_chunks",
        "undelivered_chunks", "backlog_chunks", "split_chunks", "oversized_chunks", "weights_rejected", "stalled",
        "env_steps_cut", "env_obs_clipped", "env_resets_retried"}
    assert last["env_steps_cut"] == last["env_obs_clipped"] == last["env_resets_retried"] == 0
    assert last["slot"] == 1 and last["policy_version"] == -1
    assert node.tokens == [keys.alive("actor", "a0")]
    # transitions: every start whose n steps were taken, flushed on stop; chunks of whole steps
    chunks = [P.TransitionBatch.decode(p) for p in node.sent(keys.transitions("a0"))]
    n = sum(len(c.data["action"]) for c in chunks)
    assert n == (steps - N_STEP) * E == actor.sent_transitions
    assert all(len(c.data["action"]) == 8 for c in chunks[:-1]) and [c.seq for c in chunks] == list(range(len(chunks)))
    prio = np.concatenate([c.priorities for c in chunks])
    assert prio.shape == (n,) and np.isfinite(prio).all() and (prio >= 0).all() and prio.max() > 0
    # finished training episodes, with the actor's mean epsilon
    episodes = [P.EpisodeStats.decode(p) for p in node.sent(keys.episodes("a0"))]
    assert episodes and all(e.slot == 1 and e.epsilon == pytest.approx(env_epsilons(1, 2, E).mean()) for e in episodes)
    assert sum(len(e.returns) for e in episodes) >= steps * E // 15 - E


def test_apex_actor_keeps_to_its_step_rate_cap_in_bounded_waits(tmp_path):
    cfg = _cfg(tmp_path, f"actor.max_steps_per_s={E * 100}")  # 100 batched steps/s: one per 10 ms
    actor = ApexActor(cfg, FakeNode(None), "t", "a0", slot=0, num_slots=1)
    actor.start(actor.node)
    t0, waits = time.monotonic(), 0
    while actor.steps < 20:
        waits += not actor.step(0.001)  # the loop's stop check runs between these
    elapsed = time.monotonic() - t0
    assert elapsed >= 20 * 0.010 * 0.99, "faster than the cap"
    assert waits >= 20, "each wait must be bounded by the step's timeout"
    actor.close()


def _eval_cfg(tmp_path, *sets):
    return _cfg(tmp_path, "evaluator.episodes=3", "evaluator.interval_s=0.01", "evaluator.seed_offset=0", *sets)


class Rows:
    def __init__(self):
        self.rows = []
        self.failed_writes = 0

    def write(self, source, step, values):
        self.rows.append((source, step, dict(values)))


def _net(seed):
    torch.manual_seed(seed)
    return QNetwork({"obs": ArraySpec((4,), "float32")}, 2, load_config(None, ["network.hidden=[16]"], environ={}).network)


def test_evaluator_plays_a_round_per_new_version_and_publishes_it(tmp_path):
    keys = P.Keys("t")
    node = FakeNode(weights_payload(_net(0), version=5, updates=50))
    rows = Rows()
    ev = Evaluator(_eval_cfg(tmp_path), node, "t", rows)

    def results():
        return [P.EvalResult.decode(p) for p in node.sent(keys.eval)]

    def stats():
        return _stats(node, keys, "evaluator", "evaluator")

    with running(ev.run):
        wait_for(lambda: results() and len(stats()) >= 1, what="a round and stats")
        n = len(stats())
        wait_for(lambda: len(stats()) >= n + 3, what="more stats")  # several intervals later ...
        assert len(results()) == 1, "... still one round: no newer weights"
        node.latest.set("k", weights_payload(_net(1), version=6, updates=60))
        wait_for(lambda: len(results()) == 2, what="a round of the new version")
    r5, r6 = results()
    assert (r5.version, r5.updates, r6.version, r6.updates) == (5, 50, 6, 60)
    assert r5.returns.shape == (3,) and r5.returns.dtype == np.float32 and r5.outcomes is None
    assert [row[:2] for row in rows.rows] == [("eval", 50), ("eval", 60)]
    assert rows.rows[0][2]["return_mean"] == pytest.approx(float(r5.returns.mean()))
    st = stats()[-1]
    assert st["eval_rounds"] == 2 and st["version"] == 6 and st["errors_total"] == 0
    assert node.tokens == [keys.alive("evaluator", "evaluator")]
    assert not node.sent(keys.episodes("evaluator")), "evaluation episodes are not training episodes"


def test_apex_actor_with_the_guard_as_demonstrator_acts_on_its_turns(tmp_path):
    """``actor.guard_share=1``: on a real match env with the other robot placed on the agent's
    right, each step the env's guard acts on is stepped with the guard's turn, and the actor
    counts them (``guard_actions``); ``guard_share=0`` leaves the policy's actions."""
    sets = ["env.id=zenrl/BurgerWar-v0", "env.kwargs.opponents=idle", "env.kwargs.side=red",
            "env.kwargs.lidar_noise=0.0", "env.kwargs.enemy_detector=true"]
    keys = P.Keys("t")
    for share in (1.0, 0.0):
        node = FakeNode(None)
        actor = ApexActor(_cfg(tmp_path, *sets, f"actor.guard_share={share}"), node, "t", "a0", slot=0, num_slots=1)
        actor.start(actor.node)
        assert actor.step(1.0)  # the envs reset
        for env in actor.envs.envs:
            env.unwrapped.set_poses((-0.9, 0.0, math.pi / 2), (-0.4, 0.1, 0.0))
        seen: list = []
        env_step = actor.envs.step

        def recording(actions):
            seen.append(([env.unwrapped.guard_action(o) for env, o in zip(actor.envs.envs, actor._obs["obs/enemy_seen"])],
                         actions.copy()))
            return env_step(actions)

        actor.envs.step = recording
        for _ in range(10):
            actor.step(1.0)
        actor.report(0.0)
        fired = [(g, int(a)) for gs, acts in seen for g, a in zip(gs, acts) if g >= 0]
        assert fired, "the guard never fired: the placed poses do not test it"
        if share == 1.0:
            assert all(a == g for g, a in fired)
            assert actor.report(0.0)[0]["guard_actions"] == len(fired)
        else:
            assert "guard_actions" not in actor.report(0.0)[0]
            assert any(a != g for g, a in fired)  # the policy's own actions, not the guard's
        actor.close()
