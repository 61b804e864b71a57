"""Frozen policies as match opponents in training (common/opponents.py): a checkpoint opponent
plays its network's greedy actions on its own side's observations, exported files only when the
config says so, config mistakes are one error naming the entry at start, choosers and results."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.test_tools import BW, SHORT_MATCH, make_checkpoint
from zenrl import tools
from zenrl.common.config import RunConfig, SelfPlayConfig
from zenrl.common.env_factory import make_env
from zenrl.common.errors import ConfigError
from zenrl.common.opponents import (MatchResult, Opponent, OpponentPool, SelfPlayChooser,
                                    SnapshotLeague, check_opponents, weighted_choice, wrap_opponents)
from zenrl.common.policy_io import greedy_actions, load_policy
from zenrl.games.burgerwar import geometry as geo
from zenrl.launcher.supervisor import check_env

# symmetric starts (no noise) so that the two sides' first observations mirror each other
QUIET = {**SHORT_MATCH, "lidar_noise": 0.0, "start_noise": 0.0, "match_time": 4.0}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("opp")
    match = make_checkpoint(d / "bw", BW, QUIET, seed=1)
    exported = d / "exported.pt"
    tools.export(str(match), exported)
    return {"match": match, "exported": exported,
            "image": make_checkpoint(d / "img", "zenrl/BurgerWarImage-v0", {**QUIET, "image_size": 32}),
            "cartpole": make_checkpoint(d / "cp", "CartPole-v1", {})}


def _cfg(pool: dict, kwargs: dict | None = None, **extra) -> RunConfig:
    return RunConfig.model_validate({"env": {"id": BW, "kwargs": kwargs or QUIET}, "opponents": {"pool": pool}, **extra})


class Recorder:
    """Stands between the env and its frozen opponent: records each observation the opponent
    got, the pose of the opponent's robot in its own frame at that moment, and the action."""

    def __init__(self, env):
        self.env, self.inner = env.unwrapped, env.unwrapped.opponent_policy
        self.env.opponent_policy = self
        self.calls: list[tuple[dict, np.ndarray, int]] = []

    def __call__(self, obs):
        k = 1 - self.env.agent_side
        pose = np.array(geo.to_frame(*self.env._poses[k], k))
        a = self.inner(obs)
        self.calls.append(({key: np.array(v) for key, v in obs.items()}, pose, a))
        return a


@pytest.mark.parametrize("side", ["red", "blue"])
def test_checkpoint_opponent_plays_its_greedy_actions_on_its_own_side(files, side):
    cfg = _cfg({"frozen": {"path": str(files["match"])}}, {**QUIET, "side": side})
    results = []
    env = wrap_opponents([make_env(cfg.env)], cfg, "t", seed=0, on_result=results.append)[0]
    rec = Recorder(env)
    reference = load_policy(files["match"], env.observation_space, env.action_space).net  # its own copy
    try:
        obs0, info = env.reset(seed=4)
        assert info["opponent"] == "policy" and env.opponent == "frozen" and info["side"] == side
        done, agent_poses, steps = False, [obs0["pose"]], 0
        while not done:
            obs, _, te, tr, info = env.step(steps % 3)  # the agent drives; the frozen one decides itself
            agent_poses.append(obs["pose"])
            o = 1 - env.unwrapped.agent_side
            # the command the opponent's robot got is its last action's
            assert np.allclose(env.unwrapped._cmd[o], env.unwrapped._to_cmd(rec.calls[-1][2]))
            done, steps = te or tr, steps + 1
        assert len(rec.calls) >= steps
        seen = {key: np.stack([c[0][key] for c in rec.calls]) for key in rec.calls[0][0]}
        want = greedy_actions(reference, {f"obs/{k}": v for k, v in seen.items()})  # a direct forward pass
        assert [c[2] for c in rec.calls] == want.tolist()
        assert len(set(want.tolist())) > 1  # a policy that varies its action: the comparison can fail
        # its observations are its own: its own robot's pose in its own frame...
        for o_obs, pose, _ in rec.calls:
            assert np.allclose(o_obs["pose"], [pose[0], pose[1], np.cos(pose[2]), np.sin(pose[2])], atol=1e-4)
        # ...which mirrors the agent's at the symmetric start, and differs from the agent's later
        assert np.allclose(rec.calls[0][0]["pose"], obs0["pose"], atol=1e-4)
        assert not np.allclose(seen["pose"][-1], agent_poses[len(rec.calls) - 1], atol=1e-2)
        assert len(results) == 1 and results[0].opponent == "frozen" and results[0].side == side
        assert results[0].outcome == info["outcome"] and results[0].my_score == info["my_score"]
    finally:
        env.close()


def test_a_mixed_exported_opponent_keeps_a_member_per_env_and_draws_it_per_match(files, tmp_path):
    other = make_checkpoint(tmp_path / "other", BW, QUIET, seed=5)
    mixed = tmp_path / "mixed.pt"
    tools.export(str(files["match"]), mixed, members=[str(other)])
    cfg = _cfg({"mix": {"path": str(mixed), "exported": True}})
    envs = wrap_opponents([make_env(cfg.env), make_env(cfg.env)], cfg, "t", seed=0)
    try:
        seen = [[], []]
        for _ in range(12):
            for i, env in enumerate(envs):
                env.reset()
                seen[i].append(env.seat.player.current)
        a, b = envs[0].seat.player, envs[1].seat.player
        assert a is not b and a.module is b.module  # one program, a seat per env
        assert set(seen[0]) == set(seen[1]) == {0, 1}  # each env draws both members across its matches
    finally:
        for env in envs:
            env.close()


def test_exported_opponent_needs_the_config_to_say_so(files):
    with pytest.raises(ConfigError, match=r"opponents\.pool\.ex: .*exported TorchScript.*exported: true"):
        check_opponents(_cfg({"ex": {"path": str(files["exported"])}}), make_env(_cfg({}).env))
    with pytest.raises(ConfigError, match=r"opponents\.pool\.ck: .*not a `zenrl export` file"):
        check_opponents(_cfg({"ck": {"path": str(files["match"]), "exported": True}}), make_env(_cfg({}).env))
    cfg = _cfg({"ex": {"path": str(files["exported"]), "exported": True}}, {**QUIET, "side": "blue"})
    env = wrap_opponents([make_env(cfg.env)], cfg, "t", seed=0)[0]
    rec = Recorder(env)
    net = load_policy(files["match"], env.observation_space, env.action_space).net
    try:
        env.reset(seed=1)
        for _ in range(6):
            env.step(0)
        seen = {f"obs/{k}": np.stack([c[0][k] for c in rec.calls]) for k in rec.calls[0][0]}
        assert [c[2] for c in rec.calls] == greedy_actions(net, seen).tolist()  # the file is the checkpoint's policy
    finally:
        env.close()


@pytest.mark.parametrize("pool, message", [
    ({"gone": {"path": "/nonexistent/ckpt.pt"}}, r"opponents\.pool\.gone: '/nonexistent/ckpt.pt' does not exist"),
    ({"cart": {"path": "@cartpole"}}, r"opponents\.pool\.cart: .*does not fit this env's spaces"),
    ({"img": {"path": "@image"}}, r"opponents\.pool\.img: .*does not fit this env's spaces"),
    ({"nobody": {"bot": "nobody"}}, r"opponents\.pool\.nobody: bot 'nobody': unknown opponent"),
])
def test_a_bad_entry_stops_the_run_at_start_naming_it(files, pool, message):
    pool = {n: {k: (str(files[v[1:]]) if isinstance(v, str) and v.startswith("@") else v) for k, v in e.items()}
            for n, e in pool.items()}
    cfg = _cfg(pool)
    with pytest.raises(ConfigError, match=message):
        check_env(cfg)  # what `zenrl run` does before it starts anything
    with pytest.raises(ConfigError, match=message):
        wrap_opponents([make_env(cfg.env)], cfg, "t", seed=0)  # and each actor where it starts


def test_config_shape_errors_name_the_option():
    from zenrl.common.config import load_config

    for bad, msg in [(["opponents.pool.x.weight=2"], "either a scripted `bot` or a policy file `path`"),
                     (["opponents.pool.x.bot=cheese", "opponents.pool.x.path=a.pt"], "exactly one"),
                     (["opponents.pool.x.bot=cheese", "opponents.pool.x.exported=true"], "needs a `path`"),
                     (["opponents.pool.x.path=a.pt", "opponents.pool.x.weight=0"], "opponents.pool.x.weight"),
                     (["opponents.pool.x.path=a.pt", "opponents.pool.x.pth=b"], r"opponents\.pool\.x\.pth: Extra inputs"),
                     (["opponents.pool.snapshot:x.bot=cheese"], "letters, digits")]:
        with pytest.raises(ConfigError, match=msg):
            load_config(None, bad, environ={})
    with pytest.raises(ConfigError, match="needs a match env"):
        check_opponents(RunConfig.model_validate({"opponents": {"pool": {"c": {"bot": "cheese"}}}}),
                        make_env(RunConfig().env))


def test_weighted_choice_follows_the_weights_and_bots_play_by_name():
    pool = OpponentPool(5, [Opponent("a", "bot", 1.0, bot="cheese"), Opponent("b", "bot", 3.0, bot="waypoint"),
                            Opponent("s", "snapshot", 0.0)])
    rng = np.random.default_rng(0)
    draws = [weighted_choice(pool, rng) for _ in range(4000)]
    assert "s" not in draws and abs(draws.count("b") / 4000 - 0.75) < 0.03
    assert weighted_choice(OpponentPool(5, [Opponent("s", "snapshot", 0.0)]), rng) is None  # the env's own draw
    sp = SelfPlayChooser(0.5)
    draws = [sp(pool, rng) for _ in range(4000)]
    assert abs(draws.count("s") / 4000 - 0.5) < 0.03 and abs(draws.count("b") / 4000 - 0.375) < 0.03
    cfg = _cfg({"w": {"bot": "waypoint"}, "t": {"bot": "teriyaki", "weight": 1e-9}})
    env = wrap_opponents([make_env(cfg.env)], cfg, "t", seed=0)[0]
    try:
        _, info = env.reset(seed=0)
        assert info["opponent"] == "waypoint" and env.opponent == "w"
    finally:
        env.close()


def test_a_pluggable_chooser_and_the_env_draw(files):
    """A chooser of its own (what a league plugs in) decides; None leaves the env's draw."""
    cfg = _cfg({"frozen": {"path": str(files["match"])}, "cheese": {"bot": "cheese"}})
    picks = iter(["cheese", "frozen", None])
    results: list[MatchResult] = []
    env = wrap_opponents([make_env(cfg.env)], cfg, "t", seed=0, chooser=lambda pool, rng: next(picks),
                         on_result=results.append)[0]
    try:
        for want_env, want_name in (("cheese", "cheese"), ("policy", "frozen"), ("cheese", "cheese")):
            _, info = env.reset(seed=0)
            assert (info["opponent"], env.opponent) == (want_env, want_name)
            done = False
            while not done:
                _, _, te, tr, info = env.step(0)
                done = te or tr
        assert [r.opponent for r in results] == ["cheese", "frozen", "cheese"]
        env.chooser = lambda pool, rng: "nobody"
        with pytest.raises(ValueError, match="picked 'nobody', which is not in the pool \\(frozen, cheese\\)"):
            env.reset(seed=0)
    finally:
        env.close()


def test_snapshot_league_keeps_the_pool_in_step(tmp_path):
    env = make_env(_cfg({}).env)
    pool = OpponentPool(5)
    league = SnapshotLeague(SelfPlayConfig(enabled=True, max_snapshots=2, snapshot_interval_s=1.0), tmp_path,
                            env.observation_space, env.action_space, pool=pool)
    for i, step in enumerate((5, 6, 7)):
        make_checkpoint(tmp_path, BW, QUIET, step=step)
        assert league.refresh(now=2.0 * (i + 1))
    assert pool.names("snapshot") == ["snapshot:ckpt-000000000006.pt", "snapshot:ckpt-000000000007.pt"]
    assert pool.get("snapshot:ckpt-000000000007.pt").net is league.snapshots[-1][1]
    env.close()
