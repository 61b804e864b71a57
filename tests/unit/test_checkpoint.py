"""Training state: save -> restore -> the next update is bitwise identical; atomic files, keep-K,
corrupt newest skipped; incompatible configs refused; weight versions never go back."""

import numpy as np
import pytest
import torch

from zenrl.common.config import load_config
from zenrl.common.errors import CheckpointError
from zenrl.common.specs import ArraySpec
from zenrl.learner.checkpoint import (list_checkpoints, read_checkpoint, load_latest, read_version_mark,
                                      save_checkpoint, write_version_mark)
from zenrl.learner.dqn import DQNLearner
from zenrl.learner.base import check_resume_compatible

SPEC = {"obs": ArraySpec((4,), "float32")}


def _batch(seed, B=32):
    rng = np.random.default_rng(seed)
    data = {"obs": rng.normal(size=(B, 4)).astype(np.float32), "next_obs": rng.normal(size=(B, 4)).astype(np.float32),
            "action": rng.integers(0, 2, B), "reward": rng.normal(size=B).astype(np.float32),
            "n": np.full(B, 3, np.uint8), "terminated": rng.random(B) < 0.1}
    return data, rng.random(B).astype(np.float32) + 0.5


def _learner(cfg):
    torch.manual_seed(0)
    return DQNLearner(SPEC, 2, cfg.network, cfg.learner, torch.device("cpu"))


def test_resume_next_update_is_bitwise_identical(tmp_path):
    cfg = load_config(None, ["network.hidden=[32,32]", "learner.target_update_period=3"], environ={})
    a = _learner(cfg)
    for i in range(7):
        a.update(a.batch_to_tensors(*_batch(i)))
    state = {"format": 1, "learner": a.state_dict(), "torch_rng": torch.get_rng_state(), "config": cfg.model_dump(mode="json")}
    path = save_checkpoint(tmp_path, state, a.updates, keep=3)

    b = _learner(cfg)
    loaded = read_checkpoint(path)
    b.load_state_dict(loaded["learner"])
    assert b.updates == 7 and b.beta() == a.beta()
    for i in range(7, 10):  # crosses a target-network update (period 3)
        ma, pa = a.update(a.batch_to_tensors(*_batch(i)))
        mb, pb = b.update(b.batch_to_tensors(*_batch(i)))
        assert ma == mb and np.array_equal(pa, pb)
    for (ka, va), (kb, vb) in zip(a.online.state_dict().items(), b.online.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka
    for va, vb in zip(a.target.state_dict().values(), b.target.state_dict().values()):
        assert torch.equal(va, vb)


def test_keep_k_and_corrupt_newest_is_skipped(tmp_path, caplog):
    for step in (10, 20, 30, 40):
        save_checkpoint(tmp_path, {"format": 1, "config": {}, "step": step}, step, keep=3)
    files = list_checkpoints(tmp_path)
    assert [f.name for f in files] == ["ckpt-000000000020.pt", "ckpt-000000000030.pt", "ckpt-000000000040.pt"]
    assert not list(tmp_path.glob(".*tmp*"))
    files[-1].write_bytes(files[-1].read_bytes()[:50])  # truncated newest
    state, path = load_latest(tmp_path)
    assert state["step"] == 30 and path == files[-2]
    assert "unreadable" in caplog.text


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_latest(tmp_path / "nothing")
    with pytest.raises(CheckpointError, match="does not exist"):
        read_checkpoint(tmp_path / "ckpt-000000000001.pt")


class Evil:
    """An arbitrary object: weights_only loading must refuse to unpickle it."""


def test_pickled_objects_are_refused(tmp_path):
    p = tmp_path / "ckpt-000000000001.pt"
    torch.save({"format": 1, "x": Evil()}, p)
    with pytest.raises(CheckpointError, match="unreadable"):
        read_checkpoint(p)


def test_resume_compatibility():
    cfg = load_config(None, ["network.hidden=[32,32]"], environ={})
    more_actors = load_config(None, ["network.hidden=[32,32]", "actor.num_actors=8"], environ={})
    saved = cfg.model_dump(mode="json")
    arch = "QNetwork-abc"
    check_resume_compatible(saved, more_actors, arch, arch)  # harmless change accepted
    with pytest.raises(CheckpointError, match="network differs"):
        check_resume_compatible(saved, cfg, arch, "QNetwork-def")
    with pytest.raises(CheckpointError, match="env.id"):
        check_resume_compatible(saved, load_config(None, ["env.id=Acrobot-v1"], environ={}), arch, arch)


def test_version_mark(tmp_path):
    assert read_version_mark(tmp_path) == 0
    write_version_mark(tmp_path, 41)
    write_version_mark(tmp_path, 42)
    assert read_version_mark(tmp_path) == 42


def test_version_reservation_writes_once_per_block_and_resumes_above(tmp_path, monkeypatch):
    from zenrl.learner import checkpoint as C

    writes = []
    real = C.write_version_mark
    monkeypatch.setattr(C, "write_version_mark", lambda d, v: (writes.append(v), real(d, v)))
    r = C.VersionReservation(tmp_path, block=100)
    assert r.resume_version(7) == 7            # nothing published yet
    assert r.claim(1) == 1 and read_version_mark(tmp_path) == 101
    for v in range(2, 102):                    # inside the block: no write
        r.claim(v)
    assert writes == [101]
    r.claim(102)
    assert writes == [101, 202]
    assert read_version_mark(tmp_path) == 202
    # a learner restarted from a checkpoint saved at version 50 continues above 102
    r2 = C.VersionReservation(tmp_path, block=100)
    assert r2.resume_version(50) == 202 and r2.resume_version(500) == 500
    with pytest.raises(ValueError):
        C.VersionReservation(tmp_path, block=0)
