"""The replay's checks of R2D2 sequence chunks (replay/checks.py SequenceChecker), alone and in
the replay's ingest: valid sequences pass, each broken rule is named, and the run's algo picks
the checker."""

import gymnasium as gym
import numpy as np
import pytest

import zenrl.common.envs  # noqa: F401  (registers zenrl/StatelessCartPole-v1)
from zenrl.common import protocol as P
from zenrl.common.config import load_config
from zenrl.replay.checks import ChunkChecker, SequenceChecker
from zenrl.replay.service import ReplayService, make_checker

M, H, A = 6, 4, 3
#: StatelessCartPole's bounds: x in +-4.8, theta in +-0.419
OBS = gym.spaces.Box(np.array([-4.8, -0.419], np.float32), np.array([4.8, 0.419], np.float32), dtype=np.float32)
#: per sequence: valid steps, and how the episode ends at the last one (None: it goes on)
SEQS = [(6, None), (6, "terminated"), (3, "terminated"), (1, "truncated"), (4, "truncated"), (6, None)]


def _checker(**kw):
    args = dict(max_abs_reward=1e3, max_priority=1e4)
    args.update(kw)
    return SequenceChecker.from_spaces(OBS, gym.spaces.Discrete(A), M, H, **args)


def _chunk(seed=0):
    """A chunk of valid sequences as the actor's SequenceBuilder cuts them (zero padding)."""
    rng = np.random.default_rng(seed)
    B = len(SEQS)
    d = {"obs": np.zeros((B, M + 1, 2), np.float32), "action": np.zeros((B, M), np.int64),
         "reward": np.zeros((B, M), np.float32), "terminated": np.zeros((B, M), bool),
         "truncated": np.zeros((B, M), bool), "mask": np.zeros((B, M), bool), "first": rng.random(B) < 0.5,
         "h": rng.uniform(-1, 1, (B, H)).astype(np.float32), "c": rng.uniform(-5, 5, (B, H)).astype(np.float32)}
    for i, (n, end) in enumerate(SEQS):
        d["obs"][i, :n + 1] = rng.uniform(-0.4, 0.4, (n + 1, 2))
        d["action"][i, :n] = rng.integers(0, A, n)
        d["reward"][i, :n] = 1.0
        d["mask"][i, :n] = True
        if end is not None:
            d[end][i, n - 1] = True
    return d, rng.uniform(0, 5, B).astype(np.float32)


def test_valid_sequences_pass_with_padding_outside_the_bounds():
    d, p = _chunk()
    assert _checker().check(d, p) is None and _checker().check(d, None) is None
    # padding after s_len is never read as an observation: it may be anything finite
    d["obs"][2, 5] = 100.0
    assert _checker().check(d, p) is None
    lo = gym.spaces.Box(np.array([1.0, 1.0], np.float32), np.array([2.0, 2.0], np.float32), dtype=np.float32)
    d, p = _chunk()
    for i, (n, _) in enumerate(SEQS):
        d["obs"][i, :n + 1] = 1.5  # inside [1, 2]; the zeros of the padding are not
    assert SequenceChecker.from_spaces(lo, gym.spaces.Discrete(A), M, H, 1e3, 1e4).check(d, p) is None


@pytest.mark.parametrize("mutate, reason, words", [
    (lambda d, p: d["action"].__setitem__((1, 2), A), "action_range", f"action {A} is outside 0..{A - 1}"),
    (lambda d, p: d["action"].__setitem__((0, 0), -1), "action_range", "action -1"),
    # a padded step's action too: the learner gathers Q at every step
    (lambda d, p: d["action"].__setitem__((2, 5), 9), "action_range", "action 9"),
    (lambda d, p: d["mask"].__setitem__((3, 0), False), "mask", "at least one long"),
    (lambda d, p: d["mask"].__setitem__((2, 4), True), "mask", "prefix"),
    (lambda d, p: d["terminated"].__setitem__((0, 2), True), "done_inside", "before a sequence's last valid step"),
    (lambda d, p: d["truncated"].__setitem__((4, 1), True), "done_inside", "before"),
    (lambda d, p: d["reward"].__setitem__((5, 3), 3e38), "reward_bound", "exceeds replay.max_abs_reward"),
    (lambda d, p: d["h"].__setitem__((1, 0), 1.5), "state_bound", "|h| 1.5"),
    (lambda d, p: d["c"].__setitem__((1, 0), -1e30), "state_bound", "|c| 1e+30"),
    (lambda d, p: p.__setitem__(0, 1e30), "priority_bound", "exceeds replay.max_priority"),
    (lambda d, p: d["obs"].__setitem__((0, 3, 0), 4.9), "obs_bounds", "field obs"),
    (lambda d, p: d["obs"].__setitem__((2, 3, 1), -0.5), "obs_bounds", "field obs"),  # s_len, the final observation
])
def test_each_broken_rule_is_named(mutate, reason, words):
    d, p = _chunk()
    mutate(d, p)
    r = _checker().check(d, p)
    assert r is not None and r.reason == reason and words in r.detail, r


def test_fields_dtypes_and_shapes_against_the_sequence_spec():
    cases = [
        (lambda d: d.pop("mask"), "spec", "field mask is missing"),
        (lambda d: d.__setitem__("obs", d["obs"][:, :M]), "obs_dtype", "field obs"),              # m obs, not m+1
        (lambda d: d.__setitem__("obs", d["obs"].astype(np.float64)), "obs_dtype", "field obs"),
        (lambda d: d.__setitem__("action", d["action"][:, :M - 1]), "spec", "field action"),
        (lambda d: d.__setitem__("h", np.zeros((len(SEQS), H + 1), np.float32)), "spec", "field h"),
        (lambda d: d.__setitem__("first", np.zeros((len(SEQS), 1), bool)), "spec", "field first"),
        (lambda d: d.__setitem__("n", np.ones(len(SEQS), np.uint8)), "spec", "not part of an R2D2 sequence"),
    ]
    for mutate, reason, words in cases:
        d, p = _chunk()
        mutate(d)
        r = _checker().check(d, p)
        assert r is not None and r.reason == reason and words in r.detail, (words, r)
    d, p = _chunk()
    d["meta/policy_version"] = np.zeros(len(SEQS), np.int64)  # the replay's column: only with fields_checked
    assert _checker().check(d, p, fields_checked=True) is None
    # frame mode (tests/unit/test_r2d2_frames.py): a table must be an observation field, of its dtype
    assert _checker().check_frames({"obs": np.zeros((1, 2), np.float32)}) is None
    assert _checker().check_frames({"junk": np.zeros((1, 2), np.float32)}).reason == "fields"
    assert _checker().check_frames({"obs": np.zeros((1, 2), np.float64)}).reason == "fields"


def test_obs_bounds_check_off_keeps_the_other_checks():
    d, p = _chunk()
    d["obs"][0, 0, 0] = 10.0
    assert _checker().check(d, p).reason == "obs_bounds"
    assert _checker(check_obs_bounds=False).check(d, p) is None
    d["action"][0, 0] = A
    assert _checker(check_obs_bounds=False).check(d, p).reason == "action_range"


def _cfg(tmp_path, *sets):
    return load_config(None, [f"runs_dir={tmp_path}", "algo=r2d2", "env.id=zenrl/StatelessCartPole-v1",
                              f"r2d2.sequence_length={M}", "r2d2.burn_in=2", f"r2d2.lstm_size={H}",
                              "replay.min_size=1", *sets], environ={})


def test_the_runs_algo_picks_the_checker(tmp_path):
    assert type(make_checker(_cfg(tmp_path))) is SequenceChecker
    assert type(make_checker(load_config(None, [f"runs_dir={tmp_path}"], environ={}))) is ChunkChecker


def test_the_replay_stores_sequences_and_rejects_a_bad_one_alone(tmp_path):
    svc = ReplayService(_cfg(tmp_path, "actor.envs_per_actor=2"), None, "t")
    d, p = _chunk()
    d = {k: v.copy() for k, v in d.items()}
    d["action"] = np.minimum(d["action"], 1)  # StatelessCartPole has 2 actions
    good = P.TransitionBatch(actor_id="a0", policy_version=3, seq=0, data=d, priorities=p).encode()
    bad_d = {k: v.copy() for k, v in d.items()}
    bad_d["mask"][0, 0] = False
    bad = P.TransitionBatch(actor_id="a1", policy_version=3, seq=0, data=bad_d, priorities=p).encode()
    assert svc.ingest_many([(good, "k/a0"), (bad, "k/a1"), (good, "k/a0")]) == 2 * len(SEQS)
    v = svc.stats_values()
    assert v["rejected_mask"] == 1 and v["rejected_from/a1"] == 1 and v["size"] == 2 * len(SEQS)
    rep = svc.sample_reply(P.SampleRequest(request_id=1, batch_size=4, beta=0.4))
    assert rep.status == "ok" and rep.data["obs"].shape == (4, M + 1, 2) and rep.data["h"].shape == (4, H)
    assert (rep.data["meta/policy_version"] == 3).all()
    # an Ape-X transition chunk is not a sequence
    apex = {"obs": np.zeros((2, 2), np.float32), "next_obs": np.zeros((2, 2), np.float32),
            "action": np.zeros(2, np.int64), "reward": np.zeros(2, np.float32), "n": np.ones(2, np.uint8),
            "terminated": np.zeros(2, bool)}
    assert svc.ingest(P.TransitionBatch(actor_id="a2", policy_version=0, seq=0, data=apex).encode(), "k/a2") == 0
    assert svc.stats_values()["rejected_spec"] == 1
