"""IMPALA on a frame-stacked image env, in process (no network): the actor's frame-mode, lz4
unrolls rebuild exactly the stacks it acted on, and the learner takes them (declared sizes
against the env's spec, stacks rebuilt) into an update of its conv network."""

import gymnasium as gym
import numpy as np
import torch

from tests.unit.actor_fakes import FakeNode, run_until, weights_payload
from zenrl.actor.impala import FramedUnrolls, ImpalaActor
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.common.networks import ActorCritic, obs_spec
from zenrl.learner.impala import ImpalaLearner

ENV_ID = "zenrl-test/StackedDots-v0"
E, T, K, H = 2, 8, 4, 24


class _Dots(gym.Env):
    """A dot that the actions move on a grey H x H uint8 frame (every frame differs from the
    last: the grey level counts the steps); terminates after a random 5..12 steps."""

    observation_space = gym.spaces.Box(0, 255, (H, H), np.uint8)
    action_space = gym.spaces.Discrete(3)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.x, self.end = 0, H // 2, int(self.np_random.integers(5, 13))
        return self._frame(), {}

    def step(self, action):
        self.t += 1
        self.x = int(np.clip(self.x + int(action) - 1, 0, H - 1))
        return self._frame(), float(self.x > H // 2), self.t >= self.end, False, {}

    def _frame(self):
        f = np.full((H, H), (37 * self.t) % 200, np.uint8)
        f[H // 2, self.x] = 255
        return f


if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point=lambda **kw: gym.wrappers.FrameStackObservation(_Dots(), K))


def _cfg(tmp_path, **kw):
    sets = [f"runs_dir={tmp_path}", "algo=impala", f"env.id={ENV_ID}", "env.max_episode_steps=7",
            "network.hidden=[16]", f"actor.envs_per_actor={E}", f"actor.frame_stack={K}", "actor.compress=lz4",
            f"impala.unroll_length={T}", "impala.batch_unrolls=4", "actor.episode_report_s=0.01",
            "learner.log_interval_s=0.05"] + [f"{k}={v}" for k, v in kw.items()]
    return load_config(None, sets, environ={})


def test_frame_mode_image_unrolls_end_to_end(tmp_path):
    cfg = _cfg(tmp_path)
    env = gym.make(ENV_ID)
    spec = obs_spec(env.observation_space)
    assert spec["obs"].shape == (K, H, H)
    torch.manual_seed(0)
    net = ActorCritic(spec, 3, cfg.network)
    node = FakeNode(weights_payload(net, version=2))
    actor = ImpalaActor(cfg, node, "t", "a0", 0)
    assert isinstance(actor.adder, FramedUnrolls) and actor.adder.fields == ["obs"]
    steps = []
    add = actor.adder.add

    def recording(obs, actions, extras, res):
        steps.append(({k: v.copy() for k, v in obs.items()}, res))
        return add(obs, actions, extras, res)

    actor.adder.add = recording
    key = P.Keys("t").unrolls("a0")
    run_until(lambda stop: actor.run(stop, max_unrolls=2 * E), lambda: actor.done() and len(node.sent(key)) == 2 * E,
              what="2 rounds of unrolls")
    payloads = node.sent(key)
    cuts = 0
    for i, p in enumerate(payloads):
        r, e = divmod(i, E)
        u = P.Unroll.decode(p)
        assert u.frames is not None and u.obs["obs"].shape == (T + 1, K)
        # each frame once: the stacks share K - 1 frames with their neighbours
        assert len(u.frames["obs"]) < (T + 1) * K / 2
        rec = steps[r * T:(r + 1) * T]
        full = u.resolved()
        np.testing.assert_array_equal(full.obs["obs"][:T], np.stack([o["obs"][e] for o, _ in rec]))
        np.testing.assert_array_equal(full.obs["obs"][T], rec[-1][1].obs["obs"][e])
        cut = [t for t, (_, res) in enumerate(rec) if res.truncated[e] and not res.terminated[e]]
        if cut:
            np.testing.assert_array_equal(full.final_obs["obs"], np.stack([rec[t][1].next_obs["obs"][e] for t in cut]))
        cuts += len(cut)
    assert cuts > 0, "the unrolls should hold truncations (their final stacks rebuilt from frames)"
    assert actor.adder.sent_bytes < sum(len(P.Unroll.decode(p).resolved().encode()) for p in payloads) / 4

    svc = ImpalaLearner(cfg, None, "t")
    svc.start_offline()
    for p in payloads:
        assert svc.on_unroll("zenrl/t/unrolls/a0", p) == "queued", svc.rejects.counts
    before = [q.detach().clone() for q in svc.net.parameters()]
    assert svc.step(0.01) and svc.updates == 1 and svc.env_steps_trained == 4 * T
    assert any(not torch.equal(a, b) for a, b in zip(before, svc.net.parameters()))
    assert svc.rejects.total == 0


def test_learner_refuses_unrolls_that_lie_about_the_frame_size(tmp_path):
    """A frame-mode unroll whose frames are larger than the env's: refused with reason spec and
    counted against its sender, not decompressed."""
    cfg = _cfg(tmp_path)
    svc = ImpalaLearner(cfg, None, "t")
    svc.start_offline()
    big = 2 * H
    ids = np.zeros((T + 1, K), np.int64)
    u = P.Unroll(actor_id="liar", policy_version=svc.version, seq=0, obs={"obs": ids},
                 action=np.zeros(T, np.int64), behaviour_logp=np.full(T, -1.0, np.float32),
                 reward=np.zeros(T, np.float32), terminated=np.zeros(T, bool), truncated=np.zeros(T, bool),
                 frames={"obs": np.zeros((1, big, big), np.uint8)})
    assert svc.on_unroll("zenrl/t/unrolls/liar", u.encode(codec="lz4")) == "rejected"
    assert svc.rejects.counts["spec"] == 1 and svc.ledger.values(5)["rejected_from/liar"] == 1
