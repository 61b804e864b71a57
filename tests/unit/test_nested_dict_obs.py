"""A Dict observation inside a Dict (``{"arm": {"joints", "grip"}, "cell"}``): its leaves are the
fields ``obs/arm/joints``, ``obs/arm/grip``, ``obs/cell`` everywhere: the actors' batches (they
stacked the inner Dict as one object array, and every step failed on ``KeyError: 'obs/arm/joints'``),
the networks, and an exported policy (keyed by path, ``{"arm/joints": ...}``)."""

from __future__ import annotations

import numpy as np
import torch

from tests.integration import custom_envs  # noqa: F401  (registers NestedDict-v0)
from tests.unit.test_tools import load_exported, make_checkpoint
from zenrl import tools
from zenrl.actor.batch_env import EnvBatch
from zenrl.common.config import EnvConfig
from zenrl.common.env_factory import make_env
from zenrl.common.networks import obs_spec
from zenrl.common.policy_io import ExportedPlayer, load_policy, single_to_flat
from zenrl.common.specs import obs_fields

ENV = "tests.integration.custom_envs:NestedDict-v0"
LEAVES = {"obs/arm/joints": ((3,), np.float32), "obs/arm/grip": ((1,), np.float32), "obs/cell": ((), np.int64)}


def test_the_actors_batches_name_every_leaf():
    envs = EnvBatch(EnvConfig(id=ENV), 3, seed=0)
    assert set(obs_fields(envs.single_observation_space)) == set(LEAVES)
    obs = envs.reset()
    res = envs.step(np.array([1, 0, 1]))
    for flat in (obs, res.obs, res.next_obs):
        assert {k: (v.shape[1:], v.dtype) for k, v in flat.items()} == LEAVES
        assert all(v.shape[0] == 3 for v in flat.values())
    assert res.rewards.tolist() == [1.0, 0.0, 1.0]
    for e in envs.envs:
        e.close()


def test_one_observation_flattens_like_a_batch():
    env = make_env(EnvConfig(id=ENV))
    o, _ = env.reset(seed=1)
    flat = single_to_flat(o)
    assert {k: (v.shape, v.dtype) for k, v in flat.items()} == {k: ((1, *s), d) for k, (s, d) in LEAVES.items()}
    np.testing.assert_array_equal(flat["obs/arm/joints"][0], o["arm"]["joints"])
    assert set(obs_spec(env.observation_space)) == set(LEAVES)
    env.close()


def test_export_takes_paths_and_the_player_takes_the_nested_observation(tmp_path):
    ckpt = make_checkpoint(tmp_path / "c", ENV, {})
    out = tmp_path / "policy.pt"
    meta = tools.export(str(ckpt), str(out))
    assert meta["env"] == ENV  # the module that registers it kept: `zenrl evaluate --exported` makes it again
    assert set(meta["inputs"]) == {"arm/joints", "arm/grip", "cell"}
    env = make_env(EnvConfig(id=ENV))
    policy = load_policy(ckpt, env.observation_space, env.action_space)
    env.observation_space.seed(3)
    observations = [env.observation_space.sample() for _ in range(64)]
    ref = [int(policy.batch(single_to_flat(o))[0]) for o in observations]
    assert len(set(ref)) > 1  # the comparison is not trivially constant
    ts, meta_in_file = load_exported(out)
    assert meta_in_file["inputs"]["arm/joints"] == {"shape": [3], "dtype": "float32"}
    by_path = [{"arm/joints": torch.as_tensor(o["arm"]["joints"]), "arm/grip": torch.as_tensor(o["arm"]["grip"]),
                "cell": torch.as_tensor(np.int64(o["cell"]))} for o in observations]
    assert [int(ts(x)) for x in by_path] == ref
    player = ExportedPlayer(out)
    player.check_spaces(env.observation_space, env.action_space)
    assert [player(o) for o in observations] == ref
    env.close()
