"""Semantic chunk checks and quarantine (pure: no network, no env process)."""

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from zenrl.replay.checks import ChunkChecker, Quarantine, obs_rules_from_space

CARTPOLE_OBS = gym.spaces.Box(np.array([-4.8, -np.inf, -0.418, -np.inf], np.float32),
                              np.array([4.8, np.inf, 0.418, np.inf], np.float32), dtype=np.float32)


def _checker(**kw):
    args = dict(n_step=3, max_abs_reward=1e3, max_priority=1e4)
    args.update(kw)
    return ChunkChecker.from_spaces(CARTPOLE_OBS, gym.spaces.Discrete(2), **args)


def _chunk(b=8, seed=0):
    rng = np.random.default_rng(seed)
    data = {
        "obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
        "action": rng.integers(0, 2, b),
        "reward": rng.uniform(-3, 3, b).astype(np.float32),
        "next_obs": rng.uniform(-0.4, 0.4, (b, 4)).astype(np.float32),
        "terminated": np.zeros(b, bool),
        "truncated": np.zeros(b, bool),
        "n": rng.integers(1, 4, b).astype(np.uint8),
    }
    return data, rng.uniform(0, 5, b).astype(np.float32)


def test_valid_chunk_passes():
    d, p = _chunk()
    assert _checker().check(d, p) is None
    assert _checker().check(d, None) is None
    # an unbounded dimension takes any finite value
    d["obs"][:, 1] = 1e30
    assert _checker().check(d, p) is None


@pytest.mark.parametrize("mutate, reason, words", [
    (lambda d, p: d["action"].__setitem__(3, 7), "action_range", "action 7 is outside 0..1"),
    (lambda d, p: d["action"].__setitem__(0, -1), "action_range", "action -1"),
    (lambda d, p: d["n"].__setitem__(2, 0), "n_range", "n 0 is outside 1..3"),
    (lambda d, p: d["n"].__setitem__(2, 4), "n_range", "n 4"),
    (lambda d, p: d["reward"].__setitem__(1, 3e38), "reward_bound", "exceeds replay.max_abs_reward"),
    (lambda d, p: d["reward"].__setitem__(1, -2e3), "reward_bound", "2e+03"),
    (lambda d, p: p.__setitem__(0, 1e30), "priority_bound", "exceeds replay.max_priority"),
    (lambda d, p: d["obs"].__setitem__((5, 0), 4.9), "obs_bounds", "field obs"),
    (lambda d, p: d["next_obs"].__setitem__((5, 2), -0.5), "obs_bounds", "field next_obs"),
])
def test_semantic_attacks_are_named(mutate, reason, words):
    d, p = _chunk()
    mutate(d, p)
    r = _checker().check(d, p)
    assert r is not None and r.reason == reason and words in r.detail, r


def test_spec_and_dtype_against_the_env():
    d, p = _chunk()
    d["obs"] = d["obs"].astype(np.float64)
    assert _checker().check(d, p).reason == "obs_dtype"
    d, p = _chunk()
    d["obs"] = np.zeros((8, 5), np.float32)
    assert _checker().check(d, p).reason == "obs_dtype"
    d, p = _chunk()
    del d["reward"]
    assert "reward is missing" in _checker().check(d, p).detail
    d, p = _chunk()
    d["extra"] = np.zeros((8, 1000), np.float32)  # would grow every stored item
    assert _checker().check(d, p).reason == "spec"
    d, p = _chunk()
    d["action"] = d["action"].astype(np.int32)
    assert _checker().check(d, p).reason == "spec"


def test_obs_bounds_check_off_keeps_the_other_checks():
    from zenrl.common.config import RunConfig
    from zenrl.replay.service import make_checker

    cfg = RunConfig.model_validate({"replay": {"check_obs_bounds": False}, "actor": {"n_step": 3}})
    chk = make_checker(cfg)  # CartPole-v1, built from the config as the replay does
    d, p = _chunk()
    d["obs"][0, 0] = 100.0
    assert chk.check(d, p) is None
    d["action"][0] = 2
    assert chk.check(d, p).reason == "action_range"


def test_the_replay_checks_the_fields_the_networks_take():
    """The networks' input spec and the replay's rules come from one reading of the space
    (common/specs.obs_fields): same fields, dtypes and shapes for every kind of space."""
    from zenrl.common.networks import obs_spec

    for space in (gym.spaces.Box(0, 255, (84, 84, 4), np.uint8), gym.spaces.Box(-1, 1, (4,), np.float64),
                  gym.spaces.Discrete(5, start=1),
                  gym.spaces.Dict({"lidar": gym.spaces.Box(0, 10, (3,), np.float32), "cell": gym.spaces.Discrete(9)})):
        spec, rules = obs_spec(space), obs_rules_from_space(space)
        assert {k: (s.dtype, s.shape) for k, s in spec.items()} == {k: (r.dtype, r.shape) for k, r in rules.items()}


def test_rules_for_images_discrete_and_dicts():
    img = obs_rules_from_space(gym.spaces.Box(0, 255, (84, 84, 4), np.uint8))
    assert img["obs"].dtype == "uint8" and img["obs"].low is None  # the dtype already bounds it
    disc = obs_rules_from_space(gym.spaces.Discrete(5, start=1))
    assert disc["obs"].dtype == "int64" and float(disc["obs"].low) == 1 and float(disc["obs"].high) == 5
    d = obs_rules_from_space(gym.spaces.Dict({"lidar": gym.spaces.Box(0, 10, (3,), np.float32),
                                              "free": gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)}))
    assert set(d) == {"obs/lidar", "obs/free"} and d["obs/free"].low is None
    chk = ChunkChecker(d, 3, 1, 10.0, 10.0)
    b = 4
    data = {"obs/lidar": np.full((b, 3), 5, np.float32), "obs/free": np.zeros((b, 2), np.float32),
            "next_obs/lidar": np.full((b, 3), 5, np.float32), "next_obs/free": np.zeros((b, 2), np.float32),
            "action": np.zeros(b, np.int64), "reward": np.zeros(b, np.float32), "n": np.ones(b, np.uint8),
            "terminated": np.zeros(b, bool)}
    assert chk.check(data, None) is None
    data["next_obs/lidar"][1, 2] = 10.5
    assert chk.check(data, None).detail.startswith("field next_obs/lidar")


@settings(max_examples=200, deadline=None, derandomize=True)
@given(row=st.integers(0, 7), action=st.integers(-2**62, 2**62), n=st.integers(0, 255),
       reward=st.floats(width=32, allow_nan=False, allow_infinity=False),
       prio=st.floats(min_value=0, width=32, allow_infinity=False))
def test_any_single_bad_value_is_caught(row, action, n, reward, prio):
    """One tampered value anywhere: the chunk passes iff every rule holds."""
    d, p = _chunk()
    d["action"][row], d["n"][row], d["reward"][row], p[row] = action, n, reward, prio
    r = _checker().check(d, p)
    ok = 0 <= action <= 1 and 1 <= n <= 3 and abs(reward) <= 1e3 and prio <= 1e4
    assert (r is None) == ok, (r, action, n, reward, prio)


def test_quarantine_window_duration_and_release():
    now = [0.0]
    q = Quarantine(rejections=3, window_s=10.0, duration_s=30.0, clock=lambda: now[0])
    assert not q.record("a", "action_range")
    now[0] = 11.0  # the first rejection left the window
    assert not q.record("a", "action_range")
    assert not q.record("a", "reward_bound")
    assert not q.drop("a")
    assert q.record("a", "reward_bound")  # 3 within 10 s
    assert q.drop("a") and q.drop("a") and not q.drop("b")
    assert "a (reward_bound, 2 dropped" in q.describe()
    assert q.expire() == []
    now[0] = 41.5
    assert not q.drop("a") and q.expire() == ["a"] and q.describe() == ""
    assert q.total == 1


def test_quarantine_off_and_bounded():
    q = Quarantine(rejections=0, window_s=1.0, duration_s=1.0)
    assert not any(q.record("a", "x") for _ in range(100))
    q = Quarantine(rejections=2, window_s=100.0, duration_s=1.0, max_sources=10)
    for i in range(1000):  # invented ids cannot grow memory
        q.record(f"id{i}", "x")
    assert len(q._recent) <= 10


@pytest.mark.parametrize("shape, b", [((4,), 2000), ((3000,), 5), ((2, 3), 1)])
def test_bounds_are_checked_in_every_block_and_in_the_rest(shape, b):
    box = gym.spaces.Box(-1.0, 1.0, shape, np.float32)
    chk = ChunkChecker(obs_rules_from_space(box), 2, 1, 10.0, 10.0)
    base = {"obs": np.zeros((b, *shape), np.float32), "next_obs": np.zeros((b, *shape), np.float32),
            "action": np.zeros(b, np.int64), "reward": np.zeros(b, np.float32), "n": np.ones(b, np.uint8),
            "terminated": np.zeros(b, bool)}
    assert chk.check(base, None) is None
    base["obs"][...] = 1.0  # the bound itself is inside
    assert chk.check(base, None) is None
    for row in {0, b // 2, b - 1}:
        d = {k: v.copy() for k, v in base.items()}
        d["next_obs"].reshape(b, -1)[row, -1] = np.float32(1.0000001)
        assert chk.check(d, None).reason == "obs_bounds", (row, shape)


@pytest.mark.parametrize("option, value", [("replay.max_abs_reward", "0"), ("replay.max_priority", "-1"),
                                           ("replay.quarantine_rejections", "-1"), ("replay.quarantine_s", "0"),
                                           ("learner.guard_max_bad_updates", "0"), ("a3c.max_grad_norm", "0")])
def test_new_options_are_validated_with_the_bad_value_named(option, value):
    from zenrl.common.config import load_config
    from zenrl.common.errors import ConfigError

    with pytest.raises(ConfigError, match=option.split(".")[1]) as e:
        load_config(None, [f"{option}={value}"])
    assert value in str(e.value)


def test_source_ledger_caps_names_but_never_stops_quarantining():
    """Past max_sources a new name displaces the least rejected one (bounded memory, the heaviest
    kept), and every source that keeps failing is still quarantined; internal errors are counted
    by type, the first one flagged."""
    from zenrl.common.quarantine import SourceLedger

    t = [0.0]
    led = SourceLedger(Quarantine(2, 10.0, 60.0, clock=lambda: t[0]), max_sources=3)
    for s in ("a", "b", "c"):
        assert led.rejected(s, "action_range") is False
    assert led.rejected("d", "action_range") is False and "d" in led.by_source and len(led.by_source) == 3
    assert led.rejected("d", "action_range") is True, "a source past the name cap is still quarantined"
    assert led.quarantine.is_quarantined("d")
    assert led.internal_error(ValueError("x")) is True and led.internal_error(ValueError("y")) is False
    v = led.values(top=2)
    assert v["rejected_internal/ValueError"] == 2 and v["quarantined"] == 1 and v["quarantines_total"] == 1
    assert len([k for k in v if k.startswith("rejected_from/")]) == 2
    t[0] = 100.0
    assert led.values(top=2, expire=True)["quarantined"] == 0
