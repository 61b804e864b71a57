"""zenrl average: the policy weights of several checkpoints averaged, against a mean computed
here with numpy, and its refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from zenrl import tools
from zenrl.common.checkpoints import read_checkpoint
from zenrl.common.errors import ZenrlError
from zenrl.tools.averaging import average

from tests.unit.test_tools import make_checkpoint

ROOT = Path(__file__).resolve().parents[2]


def _online(path: Path) -> dict[str, np.ndarray]:
    d = torch.load(path, map_location="cpu", weights_only=True)
    return {k: v.numpy().astype(np.float64) for k, v in d["learner"]["online"].items()}


@pytest.fixture()
def run(tmp_path):
    run = tmp_path / "runs" / "cp-apex"
    for i, step in enumerate((10, 20, 30, 40)):
        make_checkpoint(run / "checkpoints", "CartPole-v1", {}, seed=i, step=step)
    return run


def test_mean_of_the_newest_k_against_numpy(run, tmp_path):
    files = sorted((run / "checkpoints").glob("ckpt-*.pt"))
    out = tmp_path / "avg.pt"
    res = average([run], out, last=3)
    assert res["averaged"] == 3 and res["updates"] == [20, 30, 40]
    got = _online(out)
    ws = [_online(f) for f in files[1:]]
    assert set(got) == set(ws[0])
    for k in got:
        want = (ws[0][k] + ws[1][k] + ws[2][k]) / 3.0
        np.testing.assert_allclose(got[k], want, rtol=0, atol=1e-6)
        assert not np.allclose(got[k], ws[2][k])  # not simply the newest
    st = read_checkpoint(out)
    newest = read_checkpoint(files[-1])
    assert st.updates == 40 and st.arch == newest.arch and st.version == newest.version
    for k, v in newest.learner["target"].items():  # the rest of the state is the newest input's
        assert torch.equal(st.learner["target"][k], v)
    d = torch.load(out, map_location="cpu", weights_only=True)
    assert [a["file"] for a in d["averaged_from"]] == [f.name for f in files[1:]]


def test_the_average_plays_as_a_checkpoint(run, tmp_path):
    out = tmp_path / "avg.pt"
    p = subprocess.run([sys.executable, "-m", "zenrl.cli", "average", str(run / "checkpoints"), "--last", "2",
                        "--out", str(out)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.strip().splitlines()[-1])["updates"] == [30, 40]
    policy, env, cfg = tools.load_policy_env(str(out))
    try:
        obs, _ = env.reset(seed=0)
        assert policy(obs) in (0, 1) and cfg.algo == "apex"
    finally:
        env.close()


def test_files_given_one_by_one(run, tmp_path):
    files = sorted((run / "checkpoints").glob("ckpt-*.pt"))
    res = average([files[0], files[3]], tmp_path / "a.pt")
    got, a, b = _online(tmp_path / "a.pt"), _online(files[0]), _online(files[3])
    assert res["updates"] == [10, 40]
    for k in got:
        np.testing.assert_allclose(got[k], (a[k] + b[k]) / 2.0, rtol=0, atol=1e-6)


def test_refusals_name_the_file(run, tmp_path):
    files = sorted((run / "checkpoints").glob("ckpt-*.pt"))
    other = make_checkpoint(tmp_path / "a3c", "CartPole-v1", {}, algo="a3c", step=50)
    with pytest.raises(ZenrlError, match="ckpt-000000000010.pt holds algorithm apex"):
        average([files[0], other], tmp_path / "x.pt")
    with pytest.raises(ZenrlError, match="one of the checkpoints averaged"):
        average([run], files[-1], last=2)
    with pytest.raises(ZenrlError, match="named twice"):
        average([files[0], files[0]], tmp_path / "x.pt")
    with pytest.raises(ZenrlError, match="does not exist"):
        average([tmp_path / "nope"], tmp_path / "x.pt")
    with pytest.raises(ZenrlError, match="--last must be at least 1"):
        average([run], tmp_path / "x.pt", last=0)
    bad = tmp_path / "bad" / "ckpt-000000000099.pt"
    bad.parent.mkdir()
    d = torch.load(files[1], map_location="cpu", weights_only=True)
    k = next(iter(d["learner"]["online"]))
    d["learner"]["online"][k].view(-1)[0] = float("nan")
    torch.save(d, bad)
    with pytest.raises(ZenrlError, match=f"ckpt-000000000099.pt: {k} holds a non-finite weight"):
        average([files[0], bad], tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
