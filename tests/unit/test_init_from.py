"""``learner.init_from``: a fresh Ape-X learner starts from a checkpoint's online network or from
the network inside a ``zenrl export`` file (with ``learner.init_exported``); the target equals the
online network; a file that does not fit is one clear error naming it."""

import numpy as np
import pytest
import torch

from zenrl.common.checkpoints import ApexTrainingState
from zenrl.common.config import load_config
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ZenrlError
from zenrl.common.networks import obs_spec
from zenrl.common.policy_io import ExportedPlayer, greedy_actions, initial_q_weights, single_to_flat
from zenrl.common.specs import ArraySpec
from zenrl.learner.checkpoint import save_checkpoint
from zenrl.learner.dqn import DQNLearner
from tests.unit.test_checkpoint import _batch

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "models" / "burgerwar_league.pt"
SPEC = {"obs": ArraySpec((4,), "float32")}


def _learner(cfg, spec=SPEC, n=2, seed=0):
    torch.manual_seed(seed)
    return DQNLearner(spec, n, cfg.network, cfg.learner, torch.device("cpu"))


def test_from_a_checkpoint_takes_its_online_network(tmp_path):
    cfg = load_config(None, ["network.hidden=[32,32]", "learner.target_update_period=1000"], environ={})
    a = _learner(cfg)
    for i in range(5):
        a.update(a.batch_to_tensors(*_batch(i)))
    state = ApexTrainingState(arch="QNetwork-test", version=1, config=cfg.model_dump(mode="json"),
                              torch_rng=torch.get_rng_state(), learner=a.state_dict())
    path = save_checkpoint(tmp_path, state, keep=3)
    b = _learner(cfg, seed=1)  # another random start
    b.load_initial(initial_q_weights(path, exported=False), str(path))
    for (k, va), vb, vt in zip(a.online.state_dict().items(), b.online.state_dict().values(),
                               b.target.state_dict().values()):
        assert torch.equal(va, vb) and torch.equal(va, vt), k
    assert b.updates == 0  # a fresh learner: counters and optimizer start anew


@pytest.mark.parametrize("model,config", [("burgerwar_league.pt", "burgerwar_league.yaml"),
                                          ("burgerwar_pfsp.pt", "burgerwar_league_pfsp.yaml")])
def test_from_the_shipped_export_plays_as_the_exported_policy(model, config):
    """A shipped export as the learner's start, in the env of the config it was trained with."""
    shipped = ROOT / "models" / model
    cfg = load_config(str(ROOT / "configs" / config), [], environ={})
    env = make_env(cfg.env)
    try:
        spec = obs_spec(env.observation_space)
        learner = _learner(cfg, spec, int(env.action_space.n))
        learner.load_initial(initial_q_weights(shipped, exported=True), str(shipped))
        player = ExportedPlayer(shipped)
        obs, _ = env.reset(seed=123)
        rng = np.random.default_rng(0)
        agree = 0
        for t in range(40):
            mine = int(greedy_actions(learner.online, single_to_flat(obs))[0])
            agree += mine == int(player(obs))
            obs, *_ = env.step(int(rng.integers(env.action_space.n)))
        assert agree == 40
    finally:
        env.close()


def test_files_that_do_not_fit_are_named(tmp_path):
    with pytest.raises(ZenrlError, match="learner.init_exported"):
        initial_q_weights(SHIPPED, exported=False)  # a program is loaded only on request
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ZenrlError, match="junk.pt"):
        initial_q_weights(junk, exported=False)
    with pytest.raises(ZenrlError, match="not a `zenrl export` file"):
        initial_q_weights(junk, exported=True)
    cfg = load_config(None, ["network.hidden=[16]"], environ={})
    small = _learner(cfg, {"obs": ArraySpec((386,), "float32")}, 15)
    with pytest.raises(ZenrlError, match="does not fit this network"):
        small.load_initial(initial_q_weights(SHIPPED, exported=True), str(SHIPPED))


def test_only_for_q_learners():
    with pytest.raises(Exception, match="init_from is for algo apex or r2d2"):
        load_config(None, ["algo=impala", "learner.init_from=x.pt"], environ={})
