"""zenrl evaluate / play / plot / export and the policy loading of common/policy_io.py, on tiny
checkpoints written here in the learner's format (CartPole and short Burger War matches)."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from zenrl.cli import main as cli_main
from zenrl.common.config import RunConfig, SelfPlayConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ZenrlError
from zenrl.common.networks import ActorCritic, QNetwork, arch_fingerprint, num_actions, obs_spec
from zenrl.common.checkpoints import A3CTrainingState, ApexTrainingState, training_state_class
from zenrl.common.opponents import SnapshotLeague, wrap_opponents
from zenrl.common.policy_io import load_policy, read_checkpoint, sampled_actions, single_to_flat
from zenrl.common.specs import ArraySpec
from zenrl.learner.checkpoint import save_checkpoint
from zenrl import tools
from tests.conftest import own_process_group, wait_until

# a match of 3 s + 1 s sudden death at 5 decisions/s: at most 20 steps
SHORT_MATCH = {"match_time": 3.0, "sudden_death_time": 1.0, "control_hz": 5, "opponents": ["cheese"],
               "side": "random", "reward": "zero_sum", "render_size": 96}
BW = "zenrl/BurgerWar-v0"


def make_checkpoint(directory: Path, env_id: str, kwargs: dict, algo: str = "apex", seed: int = 0,
                    step: int = 10) -> Path:
    """A training state like the learner's, for a tiny randomly initialised network."""
    cfg = RunConfig.model_validate({"algo": algo, "env": {"id": env_id, "kwargs": kwargs},
                                    "network": {"hidden": [16]}})
    env = make_env(cfg.env)
    spec, n = obs_spec(env.observation_space), num_actions(env.action_space)
    env.close()
    torch.manual_seed(seed)
    schema = training_state_class(algo)
    net = schema.policy_network(spec, n, cfg.network)
    base = {"arch": arch_fingerprint(net), "version": 1, "config": cfg.model_dump(mode="json")}
    if algo == "a3c":
        state = A3CTrainingState(**base, updates=step, model=net.state_dict(), optimizer={})
    else:
        with torch.no_grad():  # a policy that does not pick one action everywhere
            for p in net.parameters():
                p.mul_(3.0)
        state = ApexTrainingState(**base, learner={"online": net.state_dict(), "target": net.state_dict(),
                                                   "optimizer": {}, "updates": step})
    return save_checkpoint(directory, state, keep=100)


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpts")
    return {"cartpole": make_checkpoint(d / "cp", "CartPole-v1", {}),
            "match": make_checkpoint(d / "bw", BW, SHORT_MATCH),
            "image": make_checkpoint(d / "img", "zenrl/BurgerWarImage-v0", {**SHORT_MATCH, "image_size": 32}),
            "a3c": make_checkpoint(d / "a3c", "CartPole-v1", {}, algo="a3c")}


def load_exported(path: Path) -> tuple[torch.jit.ScriptModule, dict]:
    """A `zenrl export` file as a bare `torch.jit.load` reads it (no zenrl): the program and its
    zenrl.json."""
    extra = {"zenrl.json": ""}
    with warnings.catch_warnings():  # torch 2.13 deprecates TorchScript (it still loads)
        warnings.simplefilter("ignore", DeprecationWarning)
        program = torch.jit.load(str(path), _extra_files=extra)
    return program, json.loads(extra["zenrl.json"])


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


# --------------------------------------------------------------------------------------------
def test_statistics():
    lo, hi = tools.wilson(9, 10)
    assert abs(lo - 0.5958) < 1e-3 and abs(hi - 0.9821) < 1e-3  # Wilson 95% for 9/10
    assert tools.wilson(0, 0) == (0.0, 1.0)
    m, lo, hi = tools.mean_ci([1.0, 2.0, 3.0])
    assert m == 2.0 and abs((hi - m) - 4.303 / np.sqrt(3)) < 1e-9
    assert abs(tools.t975(60) - 2.000) < 0.003


def test_evaluate_cartpole_cli_json(ckpts, tmp_path, capsys):
    out = tmp_path / "ev.json"
    rc = cli_main(["evaluate", "--checkpoint", str(ckpts["cartpole"]), "--episodes", "3", "--workers", "1",
                   "--no-progress", "--json", str(out)])
    assert rc == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["kind"] == "return" and last["episodes"] == 3 and "results" not in last
    full = json.loads(out.read_text())
    assert len(full["results"]) == 3
    assert full["rows"][0]["return_mean"] == pytest.approx(np.mean([r["ret"] for r in full["results"]]))


def test_evaluate_match_counts_sides_and_parallel_equals_serial(ckpts):
    kw = dict(opponents=["cheese", "teriyaki"], episodes=2, seed=5, progress=False)
    serial = tools.evaluate(str(ckpts["match"]), **kw, workers=1)
    parallel = tools.evaluate(str(ckpts["match"]), **kw, workers=2)
    assert serial["kind"] == "match" and serial["episodes"] == 4
    assert [r["opponent"] for r in serial["rows"]] == ["cheese", "teriyaki"]
    for row in serial["rows"]:
        assert row["episodes"] == 2 and row["wins"] + row["draws"] + row["losses"] == 2
        assert row["by_side"]["red"]["episodes"] == 1 and row["by_side"]["blue"]["episodes"] == 1
        lo, hi = row["win_rate_ci95"]
        assert 0.0 <= lo <= row["win_rate"] <= hi <= 1.0
    assert {r["side"] for r in serial["results"]} == {"red", "blue"}
    key = [(r["opponent"], r["side"], r["outcome"], r["my_score"], r["enemy_score"], r["length"]) for r in serial["results"]]
    assert key == [(r["opponent"], r["side"], r["outcome"], r["my_score"], r["enemy_score"], r["length"])
                   for r in parallel["results"]]
    assert serial["total"]["episodes"] == 4


def test_sampled_actions_follow_the_policy():
    torch.manual_seed(0)
    plain = RunConfig.model_validate({"network": {"orthogonal_init": False}}).network  # logits far from uniform
    net = ActorCritic({"obs": ArraySpec((4,), "float32")}, 3, plain).eval()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(4.0)
    obs = {"obs": np.random.default_rng(0).normal(size=(2, 4)).astype(np.float32)}
    with torch.no_grad():
        probs = torch.softmax(net({"obs": torch.as_tensor(obs["obs"])})[0].double(), 1).numpy()
    n = 20_000
    rng = np.random.default_rng(1)
    counts = np.zeros((2, 3))
    for _ in range(n // 100):
        for _ in range(100):
            a = sampled_actions(net, obs, rng)
            counts[[0, 1], a] += 1
    # every frequency within 5 standard errors of its probability
    se = np.sqrt(probs * (1 - probs) / n)
    assert np.all(np.abs(counts / n - probs) <= 5 * se + 1e-9), (counts / n, probs)
    assert not np.allclose(probs[0], probs[1], atol=0.05), "the two observations should differ"
    with pytest.raises(ValueError, match="actor-critic"):
        sampled_actions(QNetwork({"obs": ArraySpec((4,), "float32")}, 3, RunConfig().network), obs, rng)


def test_evaluate_sample_policy_is_seeded_per_episode(ckpts):
    kw = dict(opponents=None, episodes=4, seed=11, progress=False, policy="sample")
    a = tools.evaluate(str(ckpts["a3c"]), **kw, workers=1)
    b = tools.evaluate(str(ckpts["a3c"]), **kw, workers=2)
    greedy = tools.evaluate(str(ckpts["a3c"]), **{**kw, "policy": "greedy"}, workers=1)
    assert a["policy"] == "sample" and greedy["policy"] == "greedy"
    assert [r["ret"] for r in a["results"]] == [r["ret"] for r in b["results"]]
    assert [r["ret"] for r in a["results"]] != [r["ret"] for r in greedy["results"]]
    with pytest.raises(ZenrlError, match="actor-critic"):
        tools.evaluate(str(ckpts["cartpole"]), **kw, workers=1)


# --------------------------------------------------------------------------------------------
def test_play_match_gif(ckpts, tmp_path):
    PIL = pytest.importorskip("PIL.Image")
    out = tmp_path / "match.gif"
    res = tools.play(str(ckpts["match"]), str(out), opponent="teriyaki", side="blue", seed=3)
    assert res["opponent"] == "teriyaki" and res["side"] == "blue"
    with PIL.open(out) as im:
        assert im.size == (96, 96)
        assert im.n_frames == res["frames"] == res["steps"] + 1 >= 2


def test_play_cartpole_gif_cli(ckpts, tmp_path, capsys):
    PIL = pytest.importorskip("PIL.Image")
    pytest.importorskip("pygame")
    out = tmp_path / "cp.gif"
    assert cli_main(["play", "--checkpoint", str(ckpts["cartpole"]), "--out", str(out), "--max-steps", "5"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    with PIL.open(out) as im:
        assert im.size == (600, 400)
        assert im.n_frames == res["frames"] == res["steps"] + 1
    assert cli_main(["play", "--checkpoint", str(ckpts["cartpole"]), "--out", str(tmp_path / "x.avi")]) == 2


def test_play_of_an_env_that_does_not_render_says_so_in_one_line(tmp_path, capsys):
    from tests.integration import custom_envs  # noqa: F401  (registers NestedDict-v0: no render)

    # an env that takes no render_mode, and one that takes it but renders nothing
    for env_id, says in (("NestedDict-v0", "env.id='tests.integration.custom_envs:NestedDict-v0' takes no render_mode: "
                                           "it renders no rgb_array frames"),
                         ("IntWalk-v0", "IntWalk-v0 renders no rgb_array frames (render() gave nothing")):
        ckpt = make_checkpoint(tmp_path / env_id, f"tests.integration.custom_envs:{env_id}", {})
        assert cli_main(["play", "--checkpoint", str(ckpt), "--out", str(tmp_path / "x.gif")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(f"zenrl: error: {says}") and "Traceback" not in "".join(err), err
        assert not (tmp_path / "x.gif").exists()


# --------------------------------------------------------------------------------------------
def test_plot_png(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    run = tmp_path / "run-1"
    run.mkdir()
    with open(run / "metrics.jsonl", "w") as f:
        for i in range(20):
            f.write(json.dumps({"time": 1000.0 + 6 * i, "source": "learner", "step": 10 * i, "loss": 1.0 / (i + 1),
                                "q_mean": 0.1 * i, "updates_per_s": 30.0, "transitions_per_s": 3840.0}) + "\n")
            if i % 5 == 0:
                f.write(json.dumps({"time": 1000.0 + 6 * i, "source": "eval", "step": 10 * i,
                                    "return_mean": float(i), "return_std": 1.0}) + "\n")
        f.write('{"time": 1200.0, "source": "lear')  # torn last line of a live run
    out = tmp_path / "curves.png"
    assert cli_main(["plot", str(run), "--out", str(out), "--size", "640x480"]) == 0
    assert png_size(out) == (640, 480)
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "eval return" in res["panels"] and "learner loss" in res["panels"]


# --------------------------------------------------------------------------------------------
def _observations(env: gym.Env, n: int, seed: int) -> list:
    """Real observations of a few random steps plus samples of the observation space."""
    obs, _ = env.reset(seed=seed)
    out = [obs]
    rng = np.random.default_rng(seed)
    while len(out) < n // 2:
        obs, _, te, tr, _ = env.step(int(rng.integers(env.action_space.n)))
        out.append(obs)
        if te or tr:
            obs, _ = env.reset()
    space = env.observation_space
    subs = space.spaces.values() if isinstance(space, gym.spaces.Dict) else [space]
    if all(np.isfinite(s.low).all() and np.isfinite(s.high).all() for s in subs):
        space.seed(seed)
        out += [space.sample() for _ in range(n - len(out))]
    else:  # unbounded (CartPole): real observations with noise
        out += [rng.normal(0, 2.0, space.shape).astype(np.float32) for _ in range(n - len(out))]
    return out


def _as_tensors(obs):
    if isinstance(obs, dict):
        return {k: torch.as_tensor(np.asarray(v)) for k, v in obs.items()}
    return torch.as_tensor(np.asarray(obs))


@pytest.mark.parametrize("which", ["cartpole", "match", "image", "a3c"])
def test_export_matches_greedy_actions(ckpts, tmp_path, which):
    ckpt = ckpts[which]
    out = tmp_path / "policy.pt"
    meta = tools.export(str(ckpt), str(out))
    state = read_checkpoint(ckpt)
    env = make_env(tools.env_config_for(state.run_config()))
    policy = load_policy(ckpt, env.observation_space, env.action_space)
    with warnings.catch_warnings():  # torch 2.13 deprecates TorchScript (it still loads)
        warnings.simplefilter("ignore", DeprecationWarning)
        ts = torch.jit.load(str(out))
    observations = _observations(env, 24, seed=1)
    env.close()
    mine = [int(ts(_as_tensors(o))) for o in observations]
    ref = [int(policy.batch(single_to_flat(o))[0]) for o in observations]
    assert mine == ref
    if which in ("match", "image"):
        assert len(set(ref)) > 1  # the comparison is not trivially constant
    extra = {"zenrl.json": ""}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.load(str(out), _extra_files=extra)
    assert json.loads(extra["zenrl.json"])["n_actions"] == meta["n_actions"]


@pytest.mark.parametrize("which", ["cartpole", "match"])
def test_a_mixed_export_plays_the_member_it_seats(ckpts, tmp_path, which):
    """``zenrl export --member``: each member's actions are its own checkpoint's greedy ones;
    ExportedPlayer seats a member per match, uniformly, reproducibly per seed."""
    first = ckpts[which]
    kwargs = SHORT_MATCH if which == "match" else {}
    env_id = BW if which == "match" else "CartPole-v1"
    others = [make_checkpoint(tmp_path / f"m{i}", env_id, kwargs, seed=10 + i) for i in range(2)]
    out = tmp_path / "mix.pt"
    assert cli_main(["export", "--checkpoint", str(first), "--member", str(others[0]), "--member", str(others[1]),
                     "--out", str(out)]) == 0
    env = make_env(tools.env_config_for(read_checkpoint(first).run_config()))
    observations = _observations(env, 24, seed=2)
    refs = [[int(load_policy(c, env.observation_space, env.action_space).batch(single_to_flat(o))[0])
             for o in observations] for c in (first, *others)]
    assert len({tuple(r) for r in refs}) == 3  # three different policies: the seat is observable
    player = tools.ExportedPlayer(out)
    assert player.members == 3
    for i, ref in enumerate(refs):
        player.current = i
        assert [player(o) for o in observations] == ref, f"member {i}"
    with pytest.raises(Exception, match="out of range"):
        player.module.pick(3)
    # envs of one process share the program: each env's seat keeps its own member
    a, b = player.for_env(), player.for_env()
    a.current, b.current = 1, 2
    assert [(a(o), b(o)) for o in observations] == list(zip(refs[1], refs[2]))
    seats = []
    player.reseed(7)
    for _ in range(300):
        player.reset()
        seats.append(player.current)
    counts = np.bincount(seats, minlength=3)
    assert counts.min() > 70, counts  # uniform: 100 each expected
    player.reseed(7)
    again = []
    for _ in range(300):
        player.reset()
        again.append(player.current)
    assert again == seats
    env.close()


def test_a_mixture_refuses_members_of_another_env(ckpts, tmp_path):
    with pytest.raises(ZenrlError, match="a mixture plays one env"):
        tools.export(str(ckpts["match"]), str(tmp_path / "x.pt"), members=[str(ckpts["cartpole"])])


def test_exported_policy_loads_without_zenrl(ckpts, tmp_path):
    out = tmp_path / "policy.pt"
    tools.export(str(ckpts["match"]), str(out))
    code = ("import sys; sys.modules['zenrl'] = None\n"
            "import torch\n"
            f"p = torch.jit.load({str(out)!r})\n"
            "obs = {'lidar': torch.full((360,), 1.0), 'pose': torch.tensor([0.0, -1.3, 0.0, 1.0]),\n"
            "       'mask': torch.ones(18), 'game': torch.zeros(4)}\n"
            "a = int(p(obs)); assert 0 <= a < 5; print(a)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]


def _episodes(summary):
    return [(r["opponent"], r["side"], r["seed"], r["ret"], r["length"], r["outcome"]) for r in summary["results"]]


@pytest.mark.parametrize("which", ["match", "cartpole"])
def test_evaluate_exported_file_plays_the_same_episodes_as_its_checkpoint(ckpts, tmp_path, which):
    """``zenrl evaluate`` on an exported file: its env comes from the file's zenrl.json and it
    plays exactly the checkpoint's greedy episodes (same seeds, same actions, same outcomes)."""
    out = tmp_path / "policy.pt"
    tools.export(str(ckpts[which]), str(out))
    assert tools.is_exported(out) and not tools.is_exported(ckpts[which])
    kw = {"opponents": ["cheese"], "episodes": 2} if which == "match" else {"episodes": 3}
    ref = tools.evaluate(str(ckpts[which]), progress=False, seed=5, **kw)
    with pytest.raises(ZenrlError, match="exported TorchScript policy.*--exported"):
        tools.evaluate(str(out), progress=False, seed=5, **kw)  # a program: loaded only when asked for
    mine = tools.evaluate(str(out), progress=False, seed=5, allow_exported=True, **kw)
    assert mine["env"] == ref["env"] and _episodes(mine) == _episodes(ref)
    if which == "match":
        assert {r["side"] for r in mine["results"]} == {"red", "blue"}
    with pytest.raises(ZenrlError, match="greedy only"):
        tools.evaluate(str(out), progress=False, policy="sample", allow_exported=True, **kw)
    with pytest.raises(ZenrlError, match="already an exported policy"):
        tools.export(str(out), str(tmp_path / "again.pt"))


def test_exported_file_for_another_env_is_refused_by_name(ckpts, tmp_path):
    out = tmp_path / "cartpole.pt"
    tools.export(str(ckpts["cartpole"]), str(out))
    with pytest.raises(ZenrlError, match="observation keys"):
        tools.evaluate(str(out), env_id=BW, env_kwargs=SHORT_MATCH, opponents=["cheese"], episodes=2, progress=False,
                       allow_exported=True)
    env = make_env(RunConfig.model_validate({"env": {"id": BW, "kwargs": SHORT_MATCH}}).env)
    try:
        with pytest.raises(ZenrlError, match="cartpole.pt"):
            tools.load_player(out, env.observation_space, env.action_space, allow_exported=True)
    finally:
        env.close()


def test_evaluate_against_policy_files(ckpts, tmp_path):
    """--opponents mixes bots and frozen policies (a checkpoint and an exported file); each file
    opponent really drives the enemy robot, on both sides."""
    from zenrl.tools.evaluation import EpisodeRunner, split_opponents

    exported = tmp_path / "old.pt"
    tools.export(str(ckpts["match"]), str(exported))
    ckpt = str(ckpts["match"])
    with pytest.raises(ZenrlError, match="--exported"):
        tools.evaluate(ckpt, opponents=["cheese", ckpt, str(exported)], episodes=2, progress=False)
    summary = tools.evaluate(ckpt, opponents=["cheese", ckpt, str(exported)], episodes=2, progress=False,
                             allow_exported=True)
    assert [r["opponent"] for r in summary["rows"]] == ["cheese", ckpt, str(exported)]
    assert all(r["episodes"] == 2 for r in summary["rows"])

    runner = EpisodeRunner(ckpt, None, None, [str(exported)], allow_exported=True)
    calls = []
    inner = runner.frozen[str(exported)]
    runner.frozen[str(exported)] = lambda obs: calls.append(1) or inner(obs)
    try:
        for side in ("red", "blue"):
            before = len(calls)
            res = runner.run(tools.Job(0, 3, str(exported), side))
            assert res.outcome in ("win", "draw", "loss") and len(calls) - before >= res.length // 2
            assert runner.env.unwrapped.opponent_name == "policy"
    finally:
        runner.close()
    with pytest.raises(ZenrlError, match="'nobody'.*neither a bot"):
        split_opponents(["cheese", "nobody"])
    with pytest.raises(ZenrlError, match="neither a bot"):
        tools.evaluate(ckpt, opponents=[str(tmp_path / "missing.pt")], episodes=2, progress=False)


# --------------------------------------------------------------------------------------------
def test_selfplay_wrapper_plays_snapshots(ckpts, tmp_path):
    cfg = RunConfig.model_validate({"env": {"id": BW, "kwargs": SHORT_MATCH}, "runs_dir": str(tmp_path),
                                    "selfplay": {"enabled": True, "snapshot_prob": 1.0, "snapshot_interval_s": 1e-3}})
    envs = [make_env(cfg.env) for _ in range(2)]
    wrapped = wrap_opponents(envs, cfg, "sp", seed=0)
    try:
        _, info = wrapped[0].reset(seed=0)
        assert info["opponent"] == "cheese" and wrapped[0].opponent == "cheese"  # no snapshot yet: scripted only
        make_checkpoint(tmp_path / "sp" / "checkpoints", BW, SHORT_MATCH, step=42)
        pool = wrapped[0].pool
        assert wrapped[1].pool is pool
        for w in wrapped:
            _, info = w.reset(seed=1)
            assert info["opponent"] == "policy" and w.opponent == "snapshot:ckpt-000000000042.pt"
            done = False
            while not done:
                _, _, te, tr, info = w.step(0)
                done = te or tr
        assert pool.names("snapshot") == ["snapshot:ckpt-000000000042.pt"]
        _, info = wrapped[0].reset(seed=2, options={"opponent": "cheese"})  # explicit choice wins
        assert info["opponent"] == "cheese"
    finally:
        for w in wrapped:
            w.close()


def test_league_keeps_newest_snapshots_and_skips_bad_files(ckpts, tmp_path):
    env = make_env(RunConfig.model_validate({"env": {"id": BW, "kwargs": SHORT_MATCH}}).env)
    league = SnapshotLeague(SelfPlayConfig(enabled=True, max_snapshots=2, snapshot_interval_s=1.0), tmp_path,
                            env.observation_space, env.action_space)
    assert not league.refresh(now=0.0) and league.sample() is None
    (tmp_path / "ckpt-000000000001.pt").write_bytes(b"not a checkpoint")
    assert not league.refresh(now=2.0)
    for i, step in enumerate((5, 6, 7)):
        make_checkpoint(tmp_path, BW, SHORT_MATCH, step=step)
        assert not league.refresh(now=2.5 + 2 * i)  # interval not over yet
        assert league.refresh(now=4.0 + 2 * i)
    assert [n for n, _ in league.snapshots] == ["ckpt-000000000006.pt", "ckpt-000000000007.pt"]
    env.close()


# --------------------------------------------------------------------------------------------
def _zenrl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "zenrl.cli", *args], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[2])


def test_tools_take_the_newest_checkpoint_of_a_folder(tmp_path):
    """evaluate / play / export given a run folder or its checkpoints folder, as a user types
    them: the newest checkpoint is used, and stdout's last line is the JSON (no pybullet banner)."""
    run = tmp_path / "BurgerWar-v0-apex-1"
    make_checkpoint(run / "checkpoints", BW, SHORT_MATCH, seed=1, step=10)
    newest = make_checkpoint(run / "checkpoints", BW, SHORT_MATCH, seed=2, step=20)
    p = _zenrl("export", "--checkpoint", str(run), "--out", str(tmp_path / "p.pt"))
    assert p.returncode == 0, p.stderr
    assert "pybullet build time" not in p.stdout
    assert json.loads(p.stdout.strip().splitlines()[-1])["out"] == str(tmp_path / "p.pt")
    p = _zenrl("evaluate", "--checkpoint", str(run / "checkpoints"), "--opponents", "cheese", "--episodes", "2",
               "--workers", "2", "--no-progress")
    assert p.returncode == 0, p.stderr
    assert "pybullet build time" not in p.stdout  # nor from the worker processes
    assert json.loads(p.stdout.strip().splitlines()[-1])["checkpoint"] == str(newest)
    p = _zenrl("play", "--checkpoint", str(run), "--out", str(tmp_path / "m.gif"), "--opponent", "cheese",
               "--side", "blue", "--speedup", "10")
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res["checkpoint"] == str(newest) and res["side"] == "blue"
    assert res["fps"] <= 25 and res["frames"] < res["recorded_frames"]  # sped up by dropping frames
    empty = tmp_path / "empty-run"
    (empty / "checkpoints").mkdir(parents=True)
    p = _zenrl("export", "--checkpoint", str(empty), "--out", str(tmp_path / "q.pt"))
    assert p.returncode == 2 and "no ckpt-*.pt checkpoint in" in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_match_frames_mark_the_agent(ckpts):
    from zenrl.tools.media import SIDE_RGB

    policy, env, _ = tools.load_policy_env(str(ckpts["match"]), render_mode="rgb_array", opponents=["cheese"])
    try:
        for side in ("red", "blue"):
            frames, res = tools.record_episode(policy, env, seed=1, options={"side": side}, max_steps=2)
            assert res["side"] == side
            corner = frames[-1][0, 0]  # the border in the agent's colour
            assert tuple(int(c) for c in corner) == SIDE_RGB[side]
    finally:
        env.close()


def test_speed_up_keeps_every_kth_frame_and_the_last():
    from zenrl.tools.media import speed_up

    frames = [np.full((2, 2, 3), i, np.int32) for i in range(901)]  # a 3-minute match at 5 decisions/s
    kept, fps = speed_up(frames, 5.0, 4.0, 25.0)
    assert len(kept) == 901 and fps == 20.0
    kept, fps = speed_up(frames, 5.0, 20.0, 25.0)
    assert fps == 25.0 and [int(f[0, 0, 0]) for f in kept] == list(range(0, 901, 4))
    kept, fps = speed_up(frames[:10], 5.0, 10.0, 25.0)  # k = 2: 0, 2, ..., 8, then the last (9)
    assert [int(f[0, 0, 0]) for f in kept] == [0, 2, 4, 6, 8, 9] and fps == 25.0
    with pytest.raises(ZenrlError, match="speedup"):
        speed_up(frames, 5.0, 0.0, 25.0)


def test_evaluate_table_fits_80_columns():
    from rich.console import Console

    results = [tools.EpisodeResult(i, i, opp, "red" if i % 2 else "blue", 1.0, 100, "win" if i % 3 else "loss", 3, 1)
               for i, opp in enumerate(["clubhouse", "waypoint"] * 50)]
    summary = tools.summarize(results, match=True)
    summary.update({"env": "zenrl/BurgerWar-v0", "checkpoint": "runs/x/checkpoints/ckpt-000000123456.pt"})
    console = Console(width=80, record=True)
    console.print(tools.render_table(summary))
    text = console.export_text()
    assert max(len(x) for x in text.splitlines()) <= 80 and "…" not in text, text
    assert "66% [" in text and "clubhouse" in text and "waypoint" in text, text
    # with each side's robot-marker points (a match env's results): one more column, still 80
    for r in results:
        r.robot_points = (11, 0) if r.opponent == "waypoint" else (3, 5)
    summary = tools.summarize(results, match=True)
    rows = {r["opponent"]: r for r in summary["rows"]}
    assert rows["waypoint"]["robot_points_mean"] == 11.0 and rows["clubhouse"]["enemy_robot_points_mean"] == 5.0
    summary.update({"env": "zenrl/BurgerWar-v0", "checkpoint": "runs/x/checkpoints/ckpt-000000123456.pt"})
    console = Console(width=80, record=True)
    console.print(tools.render_table(summary))
    text = console.export_text()
    assert max(len(x) for x in text.splitlines()) <= 80 and "…" not in text, text
    assert "11.0/0.0" in text and "3.0/5.0" in text, text
    results[0].robot_points = None  # a match without them (another env): no column
    assert "robot_points_mean" not in tools.summarize(results, match=True)["rows"][0]


def test_plot_breaks_at_a_resume_and_draws_env_steps(tmp_path):
    from zenrl.tools.plotting import _break_gaps

    pts = np.array([[0.0, 1.0], [5.0, 2.0], [10.0, 3.0], [20.0, 4.0], [25.0, 5.0]])
    out = _break_gaps(pts, breaks=[15.0])  # a segment starting at t=15
    assert np.isnan(out[3]).all() and out.shape == (6, 2)
    paused = np.array([[float(t), 1.0] for t in range(0, 50, 5)] + [[4000.0, 1.0], [4005.0, 1.0]])
    assert np.isnan(_break_gaps(paused, [])).any(axis=1).sum() == 1  # an hour's pause without a summary
    pytest.importorskip("matplotlib")
    run = tmp_path / "run-2"
    run.mkdir()
    with open(run / "metrics.jsonl", "w") as f:
        for i in range(10):
            f.write(json.dumps({"time": 1000.0 + 5 * i, "source": "launcher", "step": 1000 * i,
                                "env_steps": 1000 * i, "env_steps_per_s": 200.0}) + "\n")
    res = tools.plot(run, tmp_path / "c.png", 400, 300)
    assert res["panels"] == ["env steps/s"]


def test_an_exported_file_is_never_loaded_unless_asked_for(ckpts, tmp_path, monkeypatch):
    """A `zenrl export` file is a TorchScript program: `--checkpoint` and `--opponents` refuse it
    without `--exported`, before torch.jit.load ever sees it; checkpoints need no flag."""
    import torch

    out = tmp_path / "p.pt"
    tools.export(str(ckpts["cartpole"]), str(out))
    loads = []
    real = torch.jit.load
    monkeypatch.setattr(torch.jit, "load", lambda *a, **k: loads.append(a) or real(*a, **k))
    assert cli_main(["evaluate", "--checkpoint", str(out), "--episodes", "1", "--workers", "1", "--no-progress"]) == 2
    assert cli_main(["play", "--checkpoint", str(out), "--out", str(tmp_path / "m.gif"), "--max-steps", "3"]) == 2
    assert loads == [], "an exported file reached torch.jit.load without --exported"
    assert cli_main(["evaluate", "--checkpoint", str(out), "--exported", "--episodes", "1", "--workers", "1",
                     "--no-progress"]) == 0
    assert loads, "--exported loads it"


# --------------------------------------------------------------------------------------------
# zenrl export --guard
# --------------------------------------------------------------------------------------------
GUARDED_MATCH = {**SHORT_MATCH, "enemy_detector": True, "action_set": "rich"}
# the rich action table (v in {0.22, 0, -0.15} x w in {0, 0.5233, -0.5233, 1.4, -1.4}): the
# fastest turns on the spot are (0, 1.4) and (0, -1.4), rows 5 + 3 and 5 + 4
RICH_LEFT, RICH_RIGHT = 8, 9


def _with_enemy(obs: dict, seen: float, x: float, y: float) -> dict:
    return {**obs, "enemy_seen": np.array([seen, x, y], np.float32)}


def _polar(r: float, deg: float) -> tuple[float, float]:
    return r * np.cos(np.radians(deg)), r * np.sin(np.radians(deg))


@pytest.fixture(scope="module")
def guarded_ckpt(tmp_path_factory):
    return make_checkpoint(tmp_path_factory.mktemp("guard"), BW, GUARDED_MATCH, seed=3)


def test_the_guard_turns_towards_a_near_robot_off_the_heading_and_else_lets_the_policy_act(guarded_ckpt, tmp_path):
    """Expected actions worked out by hand: the other robot seen nearer than 1.2 m and more than 30
    degrees off the heading -> the fastest turn on the spot towards it (left for y > 0, else right);
    anything else (ahead, far, unseen) -> the checkpoint's own greedy action."""
    out = tmp_path / "guarded.pt"
    meta = tools.export(str(guarded_ckpt), str(out), guard=(1.2, 30.0))
    assert meta["guard"] == {"radius_m": 1.2, "angle_deg": 30.0, "turn_left": RICH_LEFT, "turn_right": RICH_RIGHT}
    env = make_env(tools.env_config_for(read_checkpoint(guarded_ckpt).run_config()))
    policy = load_policy(guarded_ckpt, env.observation_space, env.action_space)
    base = _observations(env, 12, seed=4)
    env.close()
    player = tools.ExportedPlayer(out)
    cases = [  # (seen, (x, y)) -> expected: "L", "R" or None (the policy's own)
        (1.0, _polar(0.5, 90), "L"), (1.0, _polar(0.5, -90), "R"), (1.0, _polar(1.0, 31), "L"),
        (1.0, _polar(1.0, -31), "R"), (1.0, _polar(0.3, 150), "L"), (1.0, (-0.6, 0.0), "R"),  # dead behind
        (1.0, _polar(1.19, 120), "L"),
        (1.0, _polar(1.0, 29), None), (1.0, _polar(1.0, -29), None), (1.0, _polar(0.4, 0), None),  # ahead
        (1.0, _polar(1.21, 90), None), (1.0, _polar(2.0, 180), None),  # beyond the reach
        (0.0, _polar(0.5, 90), None), (0.0, (0.0, 0.0), None),  # not seen
    ]
    own_used = set()
    for o in base:
        for seen, (x, y), want in cases:
            ob = _with_enemy(o, seen, x, y)
            own = int(policy.batch(single_to_flat(ob))[0])
            expected = {"L": RICH_LEFT, "R": RICH_RIGHT, None: own}[want]
            assert player(ob) == expected, (seen, x, y, want)
            if want is None:
                own_used.add(own)
    assert len(own_used - {RICH_LEFT, RICH_RIGHT}) > 0  # the pass-through cases are not turns by chance
    # the same program loads without zenrl and its zenrl.json describes the guard
    ts, j = load_exported(out)
    assert j["guard"]["turn_left"] == RICH_LEFT and "guarded" in j["call"]
    assert int(ts(_as_tensors(_with_enemy(base[0], 1.0, 0.0, 0.5)))) == RICH_LEFT


def test_a_guard_around_an_exported_file_equals_the_guarded_export(guarded_ckpt, tmp_path, capsys):
    """``zenrl export --exported --checkpoint <export> --guard`` wraps an existing file (its
    checkpoint may be gone): the same actions as exporting the checkpoint with the guard; the
    users' action set turns at +-0.5233 rad/s (rows 3 and 4)."""
    plain, wrapped, direct = tmp_path / "plain.pt", tmp_path / "wrapped.pt", tmp_path / "direct.pt"
    tools.export(str(guarded_ckpt), str(plain))
    tools.export(str(guarded_ckpt), str(direct), guard=(0.9, 45.0))
    # without --exported the file is never loaded (a program)
    assert cli_main(["export", "--checkpoint", str(plain), "--out", str(wrapped), "--guard"]) == 2
    assert "--exported" in capsys.readouterr().err and not wrapped.exists()
    assert cli_main(["export", "--exported", "--checkpoint", str(plain), "--out", str(wrapped), "--guard",
                     "--guard-radius", "0.9", "--guard-angle", "45"]) == 0
    env = make_env(tools.env_config_for(read_checkpoint(guarded_ckpt).run_config()))
    obs = _observations(env, 8, seed=5)
    env.close()
    a, b = tools.ExportedPlayer(wrapped), tools.ExportedPlayer(direct)
    grid = [(1.0, *_polar(r, d)) for r in (0.3, 0.85, 0.95) for d in (0, 40, 50, 100, 180, -50, -100)]
    got = [(a(_with_enemy(o, *g)), b(_with_enemy(o, *g))) for o in obs for g in grid]
    assert all(x == y for x, y in got)
    assert {x for x, _ in got} >= {RICH_LEFT, RICH_RIGHT}
    assert a.meta["guard"] == b.meta["guard"]
    # no wrapping twice, nor more options than the guard's
    with pytest.raises(ZenrlError, match="already guarded"):
        tools.guard_exported(wrapped, tmp_path / "twice.pt")
    assert cli_main(["export", "--exported", "--checkpoint", str(plain), "--out", str(tmp_path / "m.pt"),
                     "--guard", "--member", str(guarded_ckpt)]) == 2
    assert "only writes a guarded copy" in capsys.readouterr().err
    # the users' action set
    users = make_checkpoint(tmp_path / "users", BW, {**SHORT_MATCH, "enemy_detector": True}, seed=4)
    meta = tools.export(str(users), str(tmp_path / "users.pt"), guard=(1.2, 30.0))
    assert (meta["guard"]["turn_left"], meta["guard"]["turn_right"]) == (3, 4)


def test_the_guard_refuses_a_policy_it_cannot_guard(ckpts, guarded_ckpt, tmp_path):
    with pytest.raises(ZenrlError, match="enemy_seen"):  # no enemy detector
        tools.export(str(ckpts["match"]), str(tmp_path / "a.pt"), guard=(1.2, 30.0))
    with pytest.raises(ZenrlError, match="enemy_seen"):
        tools.export(str(ckpts["cartpole"]), str(tmp_path / "b.pt"), guard=(1.2, 30.0))
    for bad, what in (((0.0, 30.0), "guard-radius"), ((7.0, 30.0), "guard-radius"), ((1.0, 180.0), "guard-angle"),
                      ((1.0, -1.0), "guard-angle"), ((float("nan"), 30.0), "guard-radius")):
        with pytest.raises(ZenrlError, match=what):
            tools.export(str(guarded_ckpt), str(tmp_path / "c.pt"), guard=bad)
    assert tools.torchscript.guard_turns([(0.2, 0.0), (0.0, 0.5), (0.0, -0.5)]) == (1, 2)
    with pytest.raises(ZenrlError, match="no such turn"):
        tools.torchscript.guard_turns([(0.2, 0.0), (0.0, 0.5)])


def test_a_guarded_mixture_seats_members_and_guards_each(guarded_ckpt, tmp_path):
    other = make_checkpoint(tmp_path / "m", BW, GUARDED_MATCH, seed=11)
    out = tmp_path / "mix.pt"
    assert cli_main(["export", "--checkpoint", str(guarded_ckpt), "--member", str(other), "--out", str(out),
                     "--guard"]) == 0
    env = make_env(tools.env_config_for(read_checkpoint(guarded_ckpt).run_config()))
    obs = [_with_enemy(o, 0.0, 0.0, 0.0) for o in _observations(env, 16, seed=6)]
    refs = [[int(load_policy(c, env.observation_space, env.action_space).batch(single_to_flat(o))[0]) for o in obs]
            for c in (guarded_ckpt, other)]
    env.close()
    assert refs[0] != refs[1]
    player = tools.ExportedPlayer(out)
    assert player.members == 2
    for i in range(2):
        player.current = i
        assert [player(o) for o in obs] == refs[i]
        assert player(_with_enemy(obs[0], 1.0, 0.0, -0.5)) == RICH_RIGHT
    # wrapping a mixed export keeps pick()
    plain = tmp_path / "mixplain.pt"
    tools.export(str(guarded_ckpt), str(plain), members=[str(other)])
    wrapped = tools.guard_exported(plain, tmp_path / "mixwrapped.pt")
    p2 = tools.ExportedPlayer(wrapped["out"])
    p2.current = 1
    assert [p2(o) for o in obs] == refs[1]


def _children(pid: int) -> set[int]:
    try:
        return {int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()}
    except OSError:
        return set()


def _ignores_sigint(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        cmd = Path(f"/proc/{pid}/cmdline").read_text(errors="replace")
    except OSError:
        return False
    mask = next((int(x.split()[1], 16) for x in status.splitlines() if x.startswith("SigIgn:")), 0)
    return "spawn_main" in cmd and bool(mask & (1 << (signal.SIGINT - 1)))


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_evaluate_with_workers_stops_on_a_signal_to_its_group(ckpts, sig):
    # Ctrl-C in a terminal signals every process of the group, the workers too; SIGTERM (kill,
    # timeout) reaches the parent only: either way the command ends at once, says so in one line
    # and leaves no worker behind (it once printed a KeyboardInterrupt traceback, then hung on
    # the pool's queue lock until killed; after SIGTERM its workers lived on as orphans)
    cmd = [sys.executable, "-m", "zenrl.cli", "evaluate", "--checkpoint", str(ckpts["cartpole"]),
           "--episodes", "100000", "--workers", "2", "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **own_process_group())
    try:
        # both workers set up (they ignore SIGINT from then on: bit 2 of SigIgn), taking jobs
        wait_until(lambda: len([c for c in _children(p.pid) if _ignores_sigint(c)]) >= 2
                   if p.poll() is None else True, 120, "evaluation workers")
        assert p.poll() is None, p.communicate()
        workers = _children(p.pid)
        time.sleep(1.0)
        if sig == "SIGINT":
            os.killpg(p.pid, signal.SIGINT)
        else:
            os.kill(p.pid, signal.SIGTERM)
        out, err = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, (p.returncode, err[-2000:])
    assert err.strip().splitlines()[-1] == "zenrl: interrupted", err[-2000:]
    assert "Traceback" not in err, err[-3000:]
    wait_until(lambda: not any(_alive(w) for w in workers), 10, "the workers to end")


def test_evaluate_json_of_one_episode_is_strict_json(ckpts, tmp_path, capsys):
    # one episode has no confidence interval: null in the output, not NaN (which JSON does not
    # have: JavaScript's JSON.parse and jq refuse the document)
    out = tmp_path / "one.json"
    assert cli_main(["evaluate", "--checkpoint", str(ckpts["cartpole"]), "--episodes", "1", "--workers", "1",
                     "--no-progress", "--json", str(out)]) == 0

    def refuse(name):
        raise AssertionError(f"{name} in the JSON")

    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1], parse_constant=refuse)
    full = json.loads(out.read_text(), parse_constant=refuse)
    assert last["rows"][0]["return_ci95"] == [None, None] == full["rows"][0]["return_ci95"], last["rows"][0]
