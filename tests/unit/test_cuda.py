"""The learners on CUDA, where a GPU is present (skipped without one; CI has none): the Ape-X
update gives the CPU's numbers, a CUDA checkpoint resumes on the CPU and on CUDA, image
observations are scaled on the device, and A3C gradients from numpy are applied on the GPU."""

import numpy as np
import pytest
import torch

from zenrl.common import protocol as P
from zenrl.common.checkpoints import ApexTrainingState
from zenrl.common.config import LearnerConfig, NetworkConfig, load_config
from zenrl.common.networks import ActorCritic, QNetwork, params_to_arrays
from zenrl.common.specs import ArraySpec
from zenrl.learner.a3c import APPLIED, GradientApplier
from zenrl.learner.checkpoint import read_checkpoint, save_checkpoint
from zenrl.learner.dqn import DQNLearner

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

SPEC = {"obs": ArraySpec((4,), "float32")}
CUDA = torch.device("cuda")
CPU = torch.device("cpu")


def _batch(seed: int, B: int = 64):
    rng = np.random.default_rng(seed)
    data = {"obs": rng.normal(size=(B, 4)).astype(np.float32), "next_obs": rng.normal(size=(B, 4)).astype(np.float32),
            "action": rng.integers(0, 2, B), "reward": rng.normal(size=B).astype(np.float32),
            "n": np.full(B, 3, np.uint8), "terminated": rng.random(B) < 0.1}
    return data, rng.random(B).astype(np.float32) + 0.5


def _pair(cfg: LearnerConfig, net: NetworkConfig):
    torch.manual_seed(0)
    cpu = DQNLearner(SPEC, 2, net, cfg, CPU)
    gpu = DQNLearner(SPEC, 2, net, cfg, CUDA)
    gpu.online.load_state_dict(cpu.online.state_dict())
    gpu.target.load_state_dict(cpu.target.state_dict())
    return cpu, gpu


@pytest.mark.parametrize("optimizer", ["adam", "rmsprop"])
def test_dqn_update_on_cuda_matches_cpu(optimizer):
    cpu, gpu = _pair(LearnerConfig(lr=1e-3, optimizer=optimizer, target_update_period=3), NetworkConfig(hidden=[64, 64]))
    assert next(gpu.online.parameters()).is_cuda and gpu._fused == (optimizer == "adam")
    for i in range(8):  # crosses two target-network copies
        mc, pc = cpu.update(cpu.batch_to_tensors(*_batch(i)))
        mg, pg = gpu.update(gpu.batch_to_tensors(*_batch(i)))
        assert pg.dtype == np.float32 and pg.shape == (64,)
        np.testing.assert_allclose(pg, pc, rtol=1e-4, atol=1e-5)
        for k in mc:
            assert mg[k] == pytest.approx(mc[k], rel=1e-4, abs=1e-5), k
    for (k, a), b in zip(cpu.online.state_dict().items(), gpu.online.state_dict().values()):
        torch.testing.assert_close(b.cpu(), a, rtol=1e-4, atol=1e-5, msg=k)
    # what the actors receive is plain numpy, whatever the learner's device
    arrays = params_to_arrays(gpu.online)
    assert all(isinstance(v, np.ndarray) and v.dtype == np.float32 for v in arrays.values())


def test_cuda_checkpoint_resumes_on_cpu_and_cuda(tmp_path):
    cfg = load_config(None, ["network.hidden=[32,32]", "learner.target_update_period=3"], environ={})
    torch.manual_seed(0)
    a = DQNLearner(SPEC, 2, cfg.network, cfg.learner, CUDA)
    for i in range(5):
        a.update(a.batch_to_tensors(*_batch(i)))
    saved = ApexTrainingState(arch="QNetwork-test", version=0, config=cfg.model_dump(mode="json"), learner=a.state_dict())
    path = save_checkpoint(tmp_path, saved, keep=2)
    state = read_checkpoint(path)  # map_location cpu, weights_only
    assert all(not v.is_cuda for v in state.policy_state().values())
    for dev in (CUDA, CPU):
        b = DQNLearner(SPEC, 2, cfg.network, cfg.learner, dev)
        b.load_state_dict(state.learner)
        assert b.updates == 5
        for p in b.online.parameters():
            assert p.device.type == dev.type
            st = b.opt.state[p]
            assert st["exp_avg"].device.type == dev.type and st["step"].device.type == dev.type
        m, prio = b.update(b.batch_to_tensors(*_batch(5)))
        assert np.isfinite(prio).all() and np.isfinite(m["loss"])
    ref, _ = a.update(a.batch_to_tensors(*_batch(5)))
    assert m["loss"] == pytest.approx(ref["loss"], rel=1e-4)  # the CPU learner picked up where CUDA stopped


def test_image_observations_scaled_on_cuda():
    spec = {"obs/image": ArraySpec((64, 64, 3), "uint8"), "obs/pose": ArraySpec((3,), "float32")}
    torch.manual_seed(0)
    net_cpu = QNetwork(spec, 5, NetworkConfig(hidden=[32]))
    net_gpu = QNetwork(spec, 5, NetworkConfig(hidden=[32])).to(CUDA)
    net_gpu.load_state_dict(net_cpu.state_dict())
    rng = np.random.default_rng(0)
    obs = {"obs/image": torch.from_numpy(rng.integers(0, 256, (6, 64, 64, 3), dtype=np.uint8)),
           "obs/pose": torch.from_numpy(rng.normal(size=(6, 3)).astype(np.float32))}
    with torch.no_grad():
        q_cpu = net_cpu(obs)
        q_gpu = net_gpu({k: v.to(CUDA) for k, v in obs.items()})
    assert q_gpu.is_cuda and q_gpu.shape == (6, 5)
    # convolutions may use TF32 on the GPU: compare at that precision
    torch.testing.assert_close(q_gpu.cpu(), q_cpu, rtol=2e-3, atol=2e-3)


def test_a3c_gradients_applied_on_cuda(tmp_path):
    cfg = load_config(None, ["algo=a3c", f"runs_dir={tmp_path}"], environ={})
    spec = {"obs": ArraySpec((4,), "float32")}
    torch.manual_seed(0)
    net_cpu = ActorCritic(spec, 2, cfg.network)
    net_gpu = ActorCritic(spec, 2, cfg.network).to(CUDA)
    net_gpu.load_state_dict(net_cpu.state_dict())
    ap_cpu = GradientApplier(net_cpu, cfg.learner, cfg.a3c)
    ap_gpu = GradientApplier(net_gpu, cfg.learner, cfg.a3c)
    rng = np.random.default_rng(1)
    for ap in (ap_cpu, ap_gpu):
        ap.next_version()
    for _ in range(3):
        g = {k: rng.normal(size=p.shape).astype(np.float32) for k, p in net_cpu.named_parameters()}
        msg = P.Gradients(worker_id="w0", version=1, steps=10, grads=g)
        oc, nc = ap_cpu.apply(msg)
        og, ng = ap_gpu.apply(msg)
        assert oc == og == APPLIED and ng == pytest.approx(nc, rel=1e-5)
    for (k, a), b in zip(net_cpu.state_dict().items(), net_gpu.state_dict().values()):
        assert b.is_cuda
        torch.testing.assert_close(b.cpu(), a, rtol=1e-4, atol=1e-5, msg=k)
