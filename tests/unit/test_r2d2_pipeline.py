"""The R2D2 building blocks together on zenrl/StatelessCartPole-v1: an actor acting with
RecurrentQNetwork.step cuts sequences with SequenceBuilder, and the learner's loss on them, with
the acting network as both online and target net, recomputes exactly the actor's initial
priorities (the stored states, final observations, masks and bootstraps agree end to end)."""

import gymnasium as gym
import numpy as np
import torch

import zenrl.common.envs  # noqa: F401
from zenrl.actor.sequences import SequenceBuilder
from zenrl.common.config import NetworkConfig
from zenrl.common.networks import obs_spec
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.learner.r2d2_loss import r2d2_loss

E, M, BURN, N, GAMMA = 4, 8, 4, 3, 0.99


def test_learner_priorities_equal_the_actors_with_the_acting_network():
    envs = [gym.make("zenrl/StatelessCartPole-v1", max_episode_steps=23) for _ in range(E)]
    torch.manual_seed(0)
    net = RecurrentQNetwork(obs_spec(envs[0].observation_space), 2, NetworkConfig(hidden=[16]), lstm_size=8)
    builder = SequenceBuilder(E, M, N, GAMMA, burn_in=BURN, block_steps=3)
    rng = np.random.default_rng(0)
    obs = np.stack([env.reset(seed=i)[0] for i, env in enumerate(envs)])
    h, c = net.initial_state(E)
    blocks = []
    with torch.no_grad():
        for _ in range(150):
            q, (h2, c2) = net.step({"obs": torch.from_numpy(obs)}, (h, c))
            act = np.where(rng.random(E) < 0.5, rng.integers(0, 2, E), q.argmax(1).numpy())
            out = [env.step(int(a)) for env, a in zip(envs, act)]
            nxt = np.stack([o[0] for o in out])
            rew = np.array([o[1] for o in out], np.float32)
            term, trunc = np.array([o[2] for o in out]), np.array([o[3] for o in out])

            def final_q(idx):
                return net.step({"obs": torch.from_numpy(nxt[idx])}, (h2[idx], c2[idx]))[0].numpy()

            blk = builder.add({"obs": obs}, q.numpy(), (h.numpy(), c.numpy()), act, rew, {"obs": nxt},
                              term, trunc, final_q)
            if blk is not None:
                blocks.append(blk)
            done = torch.from_numpy(term | trunc)
            h, c = torch.where(done[:, None], 0.0, h2), torch.where(done[:, None], 0.0, c2)
            obs = nxt.copy()
            for e in np.flatnonzero(term | trunc):
                obs[e] = envs[e].reset()[0]
    data = {k: np.concatenate([b.data[k] for b in blocks]) for k in blocks[0].data}
    prio = np.concatenate([b.priorities for b in blocks])
    assert data["truncated"].any() and data["terminated"].any() and (~data["mask"]).any()
    assert data["first"].any() and (~data["first"]).any()
    batch = {k: torch.from_numpy(v) for k, v in data.items()}
    batch["weights"] = torch.ones(len(prio))
    res = r2d2_loss(net, net, batch, burn_in=BURN, n_step=N, gamma=GAMMA)
    np.testing.assert_allclose(res.priorities.numpy(), prio, rtol=1e-4, atol=1e-5)
    assert (prio > 0).any()
    res.loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters())
