"""Training state: save -> restore -> the next update is bitwise identical; every algorithm's
learner round-trips its checkpoint (every tensor and counter); the schema reads the files of the
current format and names what a file lacks; atomic files, keep-K, corrupt newest skipped;
incompatible configs refused; weight versions never go back."""

import numpy as np
import pytest
import torch

from zenrl.common import atomic_files
from zenrl.common.checkpoints import (TRAINING_STATES, A3CTrainingState, ApexTrainingState, ImpalaTrainingState,
                                     R2D2TrainingState, TrainingState, training_state_class)
from zenrl.common.config import load_config
from zenrl.common.errors import CheckpointError
from zenrl.common.specs import ArraySpec
from zenrl.learner import checkpoint as ckmod
from zenrl.learner.checkpoint import (list_checkpoints, read_checkpoint, load_latest, read_version_mark,
                                      remove_stale_temp_files, save_checkpoint, write_version_mark)
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
    state = ApexTrainingState(arch="QNetwork-test", version=1, config=cfg.model_dump(mode="json"),
                              torch_rng=torch.get_rng_state(), learner=a.state_dict())
    path = save_checkpoint(tmp_path, state, keep=3)
    assert path.name == "ckpt-000000000007.pt"

    b = _learner(cfg)
    loaded = read_checkpoint(path)
    assert isinstance(loaded, ApexTrainingState)
    b.load_state_dict(loaded.learner)
    assert b.updates == 7 and b.beta() == a.beta()
    for i in range(7, 10):  # crosses a target-network update (period 3)
        ma, pa = a.update(a.batch_to_tensors(*_batch(i)))
        mb, pb = b.update(b.batch_to_tensors(*_batch(i)))
        assert ma == mb and np.array_equal(pa, pb)
    for (ka, va), (kb, vb) in zip(a.online.state_dict().items(), b.online.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka
    for va, vb in zip(a.target.state_dict().values(), b.target.state_dict().values()):
        assert torch.equal(va, vb)


def _a3c_state(updates: int) -> A3CTrainingState:
    return A3CTrainingState(arch="ActorCritic-test", version=updates, config={}, model={"w": torch.zeros(2)},
                            optimizer={}, updates=updates)


def test_keep_k_and_corrupt_newest_is_skipped(tmp_path, caplog):
    for step in (10, 20, 30, 40):
        save_checkpoint(tmp_path, _a3c_state(step), keep=3)
    files = list_checkpoints(tmp_path)
    assert [f.name for f in files] == ["ckpt-000000000020.pt", "ckpt-000000000030.pt", "ckpt-000000000040.pt"]
    assert not list(tmp_path.glob(".*tmp*"))
    files[-1].write_bytes(files[-1].read_bytes()[:50])  # truncated newest
    state, path = load_latest(tmp_path)
    assert state.updates == 30 and path == files[-2]
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


@pytest.mark.parametrize("content", [b"root:x:0:0:root:/root:/bin/bash\n", bytes(range(256)) * 4, b""])
def test_a_file_that_is_no_archive_is_named_as_such(tmp_path, content):
    p = tmp_path / "ckpt-000000000001.pt"
    p.write_bytes(content)
    with pytest.raises(CheckpointError, match=r"is not a PyTorch checkpoint \(torch.save writes a zip archive"):
        read_checkpoint(p)


def test_a_truncated_archive_is_unreadable(tmp_path):
    p = tmp_path / "ckpt-000000000001.pt"
    torch.save({"format": 1, "x": torch.zeros(1000)}, p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="is unreadable: "):
        read_checkpoint(p)


def test_resume_compatibility():
    cfg = load_config(None, ["network.hidden=[32,32]"], environ={})
    more_actors = load_config(None, ["network.hidden=[32,32]", "actor.num_actors=8"], environ={})
    saved = cfg.model_dump(mode="json")
    arch = "QNetwork-abc"
    check_resume_compatible(saved, more_actors, arch, arch)  # harmless change accepted
    # same settings, another network: the env's spaces give it (not the settings, which are equal)
    with pytest.raises(CheckpointError, match="network differs .* with the same network settings: the env's spaces"):
        check_resume_compatible(saved, cfg, arch, "QNetwork-def")
    with pytest.raises(CheckpointError, match=r"network differs .*'hidden': \[32, 32\].* was saved, config gives .*'hidden': \[64\]"):
        check_resume_compatible(saved, load_config(None, ["network.hidden=[64]"], environ={}), arch, "QNetwork-def")
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


# --------------------------------------------------------------------------------------------
# One schema: every algorithm's learner writes it and restores from it
# --------------------------------------------------------------------------------------------
def _train_one_step(svc) -> None:
    """One real update of ``svc`` (a learner of either algorithm), without a network."""
    if svc.schema is ApexTrainingState:
        data, w = _batch(1, B=16)
        m, prios = svc.dqn.update(svc.dqn.batch_to_tensors(data, w))
        assert prios is not None
        svc.transitions_consumed += len(prios)
        svc.version = 3
    elif svc.schema is R2D2TrainingState:
        m, B = svc.cfg.r2d2.sequence_length, 4
        rng = np.random.default_rng(1)
        data = {"obs": rng.normal(size=(B, m + 1, 4)).astype(np.float32), "action": rng.integers(0, 2, (B, m)),
                "reward": np.ones((B, m), np.float32), "terminated": np.zeros((B, m), bool),
                "mask": np.ones((B, m), bool), "first": np.array([True, False, False, True]),
                "h": np.zeros((B, svc.cfg.r2d2.lstm_size), np.float32),
                "c": np.zeros((B, svc.cfg.r2d2.lstm_size), np.float32)}
        m_, prios = svc.dqn.update(svc.dqn.batch_to_tensors(data, np.ones(B, np.float32)))
        assert prios is not None
        svc.transitions_consumed += len(prios)
        svc.version = 3
    elif svc.schema is ImpalaTrainingState:
        from zenrl.common import protocol as P

        svc.start_offline()
        T, B = svc.cfg.impala.unroll_length, svc.cfg.impala.batch_unrolls
        rng = np.random.default_rng(0)
        for i in range(B):
            u = P.Unroll(actor_id="a0", policy_version=svc.version, seq=i,
                         obs={"obs": rng.uniform(-0.1, 0.1, (T + 1, 4)).astype(np.float32)},
                         action=rng.integers(0, 2, T), behaviour_logp=np.full(T, np.log(0.5), np.float32),
                         reward=np.ones(T, np.float32), terminated=np.zeros(T, bool), truncated=np.zeros(T, bool))
            assert svc.on_unroll("k/a0", u.encode()) == "queued"
        assert svc.step(0.01)
        # it published weights, which reserved versions (a resumed learner would continue above
        # the reservation, tested above); like the other branches, compare without one
        from zenrl.learner.checkpoint import VERSION_MARK

        (svc.run_dir / VERSION_MARK).unlink()
    else:
        from zenrl.common import protocol as P

        svc.applier.next_version()
        g = {k: np.full(p.shape, 0.1, np.float32) for k, p in svc.net.named_parameters()}
        assert svc.handle("k/w0", P.Gradients(worker_id="w0", version=1, steps=10, grads=g).encode()) == "applied"


def _assert_same(a, b, where="state"):
    """Every tensor equal and every counter equal, recursively."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (where, set(a) ^ set(b))
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)


@pytest.mark.parametrize("algo", sorted(TRAINING_STATES))
def test_every_algorithm_round_trips_its_checkpoint(tmp_path, algo):
    from zenrl.algorithms import ALGORITHMS

    alg = ALGORITHMS[algo]
    cfg = load_config(None, [f"runs_dir={tmp_path}", f"algo={algo}", "network.hidden=[8]"], environ={})
    svc = alg.learner(cfg, None, "rt")
    _train_one_step(svc)
    saved = svc.training_state()
    assert type(saved) is alg.checkpoint and saved.updates == 1
    path = svc.save()
    assert path.name == "ckpt-000000000001.pt"

    torch.manual_seed(12345)  # the fresh learner's random state differs until it restores
    again = alg.learner(cfg, None, "rt", resume="require")
    restored = again.training_state()
    assert type(restored) is alg.checkpoint
    a, b = saved.to_dict(), restored.to_dict()
    a.pop("saved_at"), b.pop("saved_at")
    _assert_same(a, b)
    assert again.updates == svc.updates == 1 and again.current_version() == svc.current_version()
    # what tools and self-play read: the same policy network
    _assert_same(dict(read_checkpoint(path).policy_state()), dict(svc.training_state().policy_state()))


def test_files_of_the_current_format_load(tmp_path):
    """The layout checkpoints already on disk have (format 1): a run resumed after an upgrade
    and every tool must read it."""
    cfg = load_config(None, ["network.hidden=[8]"], environ={}).model_dump(mode="json")
    w = {"trunk.0.weight": torch.ones(8, 4)}
    apex = {"format": 1, "algo": "apex", "arch": "QNetwork-x", "version": 7, "transitions_consumed": 640,
            "learner": {"online": w, "target": w, "optimizer": {}, "updates": 20}, "torch_rng": torch.get_rng_state(),
            "config": cfg, "saved_at": 1.0}
    a3c = {"format": 1, "algo": "a3c", "arch": "ActorCritic-x", "version": 5, "updates": 30, "model": w,
           "optimizer": {}, "env_steps_trained": 600, "torch_rng": torch.get_rng_state(), "config": cfg, "saved_at": 2.0}
    for name, d, updates in (("apex", apex, 20), ("a3c", a3c, 30)):
        p = tmp_path / f"{name}.pt"
        torch.save(d, p)
        s = read_checkpoint(p)
        assert type(s) is TRAINING_STATES[name] and s.updates == updates and s.version == d["version"]
        assert torch.equal(s.policy_state()["trunk.0.weight"], w["trunk.0.weight"])
        assert s.run_config().network.hidden == [8]
        _assert_same(s.to_dict(), d)  # written back, the same layout
    no_algo = {k: v for k, v in apex.items() if k != "algo"}  # the earliest files named no algo: Ape-X
    assert isinstance(TrainingState.from_dict(no_algo), ApexTrainingState)


def test_a_file_the_schema_cannot_read_is_a_clear_error():
    cfg = {"algo": "apex"}
    with pytest.raises(CheckpointError, match=r"\(apex\) lacks arch, learner"):
        TrainingState.from_dict({"format": 1, "algo": "apex", "version": 1, "config": cfg})
    with pytest.raises(CheckpointError, match="unknown algorithm 'ppo'"):
        TrainingState.from_dict({"format": 1, "algo": "ppo", "config": cfg})
    with pytest.raises(CheckpointError, match="format 2"):
        TrainingState.from_dict({"format": 2, "algo": "apex", "config": cfg})
    with pytest.raises(CheckpointError, match="not a zenrl training state"):
        TrainingState.from_dict({"weights": 1})
    with pytest.raises(CheckpointError, match="unknown algorithm"):
        training_state_class("dqn")


def test_writes_are_durable_and_a_failed_one_leaves_the_old_state(tmp_path, monkeypatch):
    """The folder is fsynced after each rename (the new name is on disk, not only the data); a
    write that fails midway (a full disk) leaves the previous checkpoint and mark, and no temp file."""
    synced = []
    real = atomic_files.fsync_dir
    monkeypatch.setattr(atomic_files, "fsync_dir", lambda d: synced.append(d) or real(d))
    monkeypatch.setattr(ckmod, "fsync_dir", atomic_files.fsync_dir)
    save_checkpoint(tmp_path, _a3c_state(10), keep=3)
    write_version_mark(tmp_path, 7)
    assert synced == [tmp_path, tmp_path]

    def full_disk(*_a, **_k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(ckmod.torch, "save", full_disk)
    with pytest.raises(OSError, match="No space"):
        save_checkpoint(tmp_path, _a3c_state(20), keep=3)
    assert [f.name for f in list_checkpoints(tmp_path)] == ["ckpt-000000000010.pt"]
    assert not list(tmp_path.glob(".*tmp*")), "a failed write must not leave its temp file"
    assert load_latest(tmp_path)[0].updates == 10 and read_version_mark(tmp_path) == 7


def test_temp_files_of_killed_writes_are_removed_when_a_learner_starts(tmp_path):
    from zenrl.learner.base import LearnerBase

    cfg = load_config(None, ["runs_dir=" + str(tmp_path)])
    ck = tmp_path / "r1" / "checkpoints"
    ck.mkdir(parents=True)
    killed = [ck / ".ckpt-000000000050.pt.tmp-4242", tmp_path / "r1" / ".weights_version.tmp-4242"]
    for p in killed:
        p.write_bytes(b"half a file")
    keep = ck / "ckpt-000000000040.pt"
    keep.write_bytes(b"x")
    LearnerBase(cfg, None, "r1", "learner")
    assert not any(p.exists() for p in killed) and keep.exists()
    assert remove_stale_temp_files(tmp_path / "nowhere") == []


def test_a_version_mark_the_disk_refuses_does_not_stop_publishing(tmp_path, monkeypatch):
    """A full disk when the mark must move: the version is still handed out, the failure is
    counted, the mark is not advanced in memory (so it is retried), and written once the disk
    takes it again."""
    from zenrl.learner.checkpoint import VersionReservation

    r = VersionReservation(tmp_path, block=10)
    assert r.claim(1) == 1 and read_version_mark(tmp_path) == 11
    real = ckmod.write_version_mark
    full = [True]

    def write(d, v):
        if full[0]:
            raise OSError(28, "No space left on device")
        real(d, v)
    monkeypatch.setattr(ckmod, "write_version_mark", write)
    for v in range(2, 16):
        assert r.claim(v) == v
    assert r.mark_errors == 1 and r.reserved == 11 and read_version_mark(tmp_path) == 11  # retried only later
    full[0] = False
    monkeypatch.setattr(ckmod, "MARK_RETRY_S", 0.0)
    r._retry_at = 0.0
    assert r.claim(16) == 16 and r.reserved == 26 and read_version_mark(tmp_path) == 26
