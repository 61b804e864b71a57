"""Semantic checks of IMPALA unrolls against the env's spaces (common/unroll_checks.py): a valid
unroll passes, and each rule (length, fields, dtypes, action range, reward bound, log-prob range,
logits consistency, observation bounds in obs and final_obs) names itself when broken."""

import gymnasium as gym
import numpy as np
import pytest

from zenrl.common import protocol as P
from zenrl.common.specs import obs_rules_from_space as obs_rules
from zenrl.common.unroll_checks import UnrollChecker

T = 4
BOX = gym.spaces.Box(low=np.array([-1.0, -2.0, -np.inf], np.float32), high=np.array([1.0, 2.0, np.inf], np.float32))
DICT = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (2, 3), np.uint8), "cell": gym.spaces.Discrete(5, start=1),
                        "pose": gym.spaces.Box(-1.0, 1.0, (2,), np.float32)})


def _logits_and_actions(seed=0, n=3):
    rng = np.random.default_rng(seed)
    logits = rng.normal(size=(T, n)).astype(np.float32)
    a = rng.integers(0, n, T).astype(np.int64)
    z = logits.astype(np.float64)
    logp = z[np.arange(T), a] - np.log(np.exp(z).sum(1))
    return logits, a, logp.astype(np.float32)


def _box_unroll(**over):
    logits, a, logp = _logits_and_actions()
    obs = np.zeros((T + 1, 3), np.float32)
    obs[:, 2] = 1e6  # unbounded dimension
    trunc = np.zeros(T, bool)
    trunc[1] = True
    kw = dict(actor_id="a0", policy_version=1, seq=0, obs={"obs": obs}, action=a, behaviour_logp=logp,
              reward=np.ones(T, np.float32), terminated=np.zeros(T, bool), truncated=trunc,
              final_obs={"obs": np.array([[0.5, -1.5, 0.0]], np.float32)}, behaviour_logits=logits)
    kw.update(over)
    return P.Unroll(**kw)


def _checker(**kw):
    return UnrollChecker.from_spaces(BOX, gym.spaces.Discrete(3), max_abs_reward=10.0, **kw)


def _reason(checker, u):
    bad = checker.check(u)
    return None if bad is None else bad.reason


def test_valid_unroll_passes():
    assert _checker(unroll_length=T).check(_box_unroll()) is None
    assert _checker().check(_box_unroll(behaviour_logits=None)) is None


def _obs_with(row, col, value):
    obs = np.zeros((T + 1, 3), np.float32)
    obs[row, col] = value
    return {"obs": obs}


CASES = {
    "length": (dict(), dict(unroll_length=T + 1)),
    "spec": (dict(obs={"obs/x": np.zeros((T + 1, 3), np.float32)},
                  final_obs={"obs/x": np.zeros((1, 3), np.float32)}), {}),
    "obs_dtype": (dict(obs={"obs": np.zeros((T + 1, 4), np.float32)}, final_obs={"obs": np.zeros((1, 4), np.float32)}), {}),
    "action_range": (dict(action=np.array([0, 1, 3, 0], np.int64)), {}),
    "action_negative": (dict(action=np.array([0, -1, 2, 0], np.int64)), {}),
    "reward_bound": (dict(reward=np.array([1, -11, 0, 0], np.float32)), {}),
    "logp_positive": (dict(behaviour_logp=np.array([-0.1, 0.01, -1, -1], np.float32), behaviour_logits=None), {}),
    "logp_too_negative": (dict(behaviour_logp=np.array([-0.1, -1e4, -1, -1], np.float32), behaviour_logits=None), {}),
    "logits_actions": (dict(behaviour_logits=np.zeros((T, 4), np.float32)), {}),
    "logp_mismatch": (dict(behaviour_logits=np.zeros((T, 3), np.float32)), {}),
    "obs_bounds_low": (dict(obs=_obs_with(2, 0, -1.01)), {}),
    "obs_bounds_high_last_row": (dict(obs=_obs_with(T, 1, 2.5)), {}),
    "final_obs_bounds": (dict(final_obs={"obs": np.array([[0.0, 3.0, 0.0]], np.float32)}), {}),
}
EXPECTED = {"action_negative": "action_range", "logp_positive": "logp_range", "logp_too_negative": "logp_range",
            "logits_actions": "spec", "obs_bounds_low": "obs_bounds", "obs_bounds_high_last_row": "obs_bounds",
            "final_obs_bounds": "obs_bounds"}


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_rule_names_itself(case):
    over, ckw = CASES[case]
    u = _box_unroll(**over)
    P.Unroll.decode(u.encode())  # well-formed on the wire: only the semantic check refuses it
    assert _reason(_checker(**ckw), u) == EXPECTED.get(case, case)


def test_obs_bounds_can_be_skipped():
    assert _checker(check_obs_bounds=False).check(_box_unroll(obs=_obs_with(2, 0, -5.0))) is None


def test_dict_space_with_image_and_discrete():
    rules = obs_rules(DICT)
    # a uint8 image in [0, 255] is bounded by its dtype alone; a Discrete by its range
    assert rules["obs/image"].low is None and rules["obs/cell"].low is not None and rules["obs/cell"].dtype == "int64"
    chk = UnrollChecker(rules, n_actions=2, max_abs_reward=1.0)
    obs = {"obs/image": np.full((T + 1, 2, 3), 255, np.uint8), "obs/cell": np.full(T + 1, 5, np.int64),
           "obs/pose": np.zeros((T + 1, 2), np.float32)}
    u = P.Unroll("a0", 0, 0, obs, np.zeros(T, np.int64), np.full(T, -0.5, np.float32), np.zeros(T, np.float32),
                 np.zeros(T, bool), np.zeros(T, bool))
    assert chk.check(u) is None
    bad = dict(obs, **{"obs/cell": np.zeros(T + 1, np.int64)})  # Discrete(5, start=1): 0 is out of range
    assert chk.check(P.Unroll("a0", 0, 0, bad, u.action, u.behaviour_logp, u.reward, u.terminated, u.truncated)).reason == "obs_bounds"
    wrong = dict(obs, **{"obs/image": obs["obs/image"].astype(np.float32)})
    assert chk.check(P.Unroll("a0", 0, 0, wrong, u.action, u.behaviour_logp, u.reward, u.terminated, u.truncated)).reason == "obs_dtype"


def test_needs_discrete_or_bounded_box_actions():
    assert UnrollChecker.from_spaces(BOX, gym.spaces.Box(-1, 1, (2,)), max_abs_reward=1.0).continuous
    with pytest.raises(ValueError, match="finite bounds"):
        UnrollChecker.from_spaces(BOX, gym.spaces.Box(-np.inf, 1, (2,)), max_abs_reward=1.0)
    with pytest.raises(ValueError, match="Discrete"):
        UnrollChecker.from_spaces(BOX, gym.spaces.MultiDiscrete([2, 2]), max_abs_reward=1.0)
