"""What an IMPALA unroll must *mean* before the learner trains on it. Pure (no zenoh), unit-tested.

:class:`~zenrl.common.protocol.Unroll` decoding already refuses what is malformed (dtypes, T
mismatches, NaN/Inf). A well-formed unroll can still wreck the learner: an action index the
policy does not have crashes ``gather``; a reward of 1e30 or a behaviour log-probability of
-1e30 (an importance ratio of e^1e30) turns the loss into inf. :class:`UnrollChecker` holds the
env's spaces and the configured bounds and names the first rule an unroll breaks, like
``replay/checks.py`` does for Ape-X transitions (the learner quarantines repeat offenders the
same way).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from zenrl.common.protocol import DEFAULT_MAX_DECODED_BYTES, DecodeLimits, Unroll
from zenrl.common.networks import LOG_STD_MIN, is_continuous, policy_actions
from zenrl.common.specs import ObsRule, Rejection, obs_rules_from_space

#: Largest |action| a continuous unroll may carry (normalised units: the env clips to [-1, 1];
#: an honest Gaussian policy's samples stay within a few of its standard deviations of a mean
#: the learner keeps near that range).
MAX_ABS_ACTION = 1e3


class UnrollChecker:
    """Checks an :class:`Unroll` against the env's spec and the run's bounds.

    ``rules``: the observation fields (:func:`~zenrl.common.specs.obs_rules_from_space`); ``n_actions``: actions in
    ``0..n_actions-1``; ``max_abs_reward``: bound on ``|reward|``; ``unroll_length``: the T every
    unroll must have (None: any); ``min_logp``: behaviour log-probabilities must lie in
    ``[min_logp, logp_tolerance]`` (a probability, with float32 rounding slack);
    ``check_obs_bounds`` False skips the observations' bounds (dtypes and shapes still count).
    With behaviour logits, their log-softmax at the action taken must match ``behaviour_logp``
    within ``logp_match_tolerance``.

    ``continuous``: actions are float32[T, n_actions] (a Box normalised to [-1, 1]: the Gaussian
    policy's samples before the env clips them), each within ``max_abs_action``; the behaviour
    log-densities may then be positive, up to what the narrowest Gaussian the learner allows
    gives (``n_actions * (-LOG_STD_MIN - log(2 pi) / 2)``), and behaviour logits are refused
    (there are none to send)."""

    def __init__(self, rules: Mapping[str, ObsRule], n_actions: int, max_abs_reward: float,
                 unroll_length: int | None = None, min_logp: float = -1000.0, logp_tolerance: float = 1e-4,
                 logp_match_tolerance: float = 1e-3, check_obs_bounds: bool = True, continuous: bool = False,
                 max_abs_action: float = MAX_ABS_ACTION) -> None:
        if n_actions < 1:
            raise ValueError(f"n_actions must be >= 1, got {n_actions}")
        self.rules = dict(rules)
        self.n_actions = int(n_actions)
        self.continuous = bool(continuous)
        self.max_abs_action = float(max_abs_action)
        self.max_logp = self.n_actions * (-LOG_STD_MIN - 0.5 * math.log(2 * math.pi)) if continuous else 0.0
        self.max_abs_reward = float(max_abs_reward)
        self.unroll_length = unroll_length
        self.min_logp = float(min_logp)
        self.logp_tolerance = float(logp_tolerance)
        self.logp_match_tolerance = float(logp_match_tolerance)
        self.check_obs_bounds = check_obs_bounds

    @classmethod
    def from_spaces(cls, observation_space: Any, action_space: Any, max_abs_reward: float, **kw: Any) -> "UnrollChecker":
        n = policy_actions(action_space)  # Discrete, or a 1-D Box with finite bounds; ValueError otherwise
        return cls(obs_rules_from_space(observation_space), int(n), max_abs_reward, continuous=is_continuous(n), **kw)

    def decode_limits(self, max_decoded_bytes: int = DEFAULT_MAX_DECODED_BYTES) -> DecodeLimits:
        """What ``Unroll.decode`` should admit for this env (``limits=``): compressed arrays only
        for the env's uint8 observation fields (``obs.<field>``, ``final_obs.<field>``), with
        the field's shape per row, and in frame mode ``frames.<field>`` with one frame's shape
        (the stack axis dropped), checked with the decoded-bytes cap before decompressing."""
        packed = {}
        for k, rule in self.rules.items():
            if np.dtype(rule.dtype) == np.uint8:
                packed[f"obs.{k}"] = packed[f"final_obs.{k}"] = (tuple(rule.shape),)
                if len(rule.shape) >= 2:  # frame mode: the distinct frames of k-frame stacks
                    packed[f"frames.{k}"] = (tuple(rule.shape[1:]),)
        return DecodeLimits(max_decoded_bytes, packed)

    def check(self, u: Unroll) -> Rejection | None:
        """None if the learner may train on ``u``, else the first rule it breaks."""
        T = u.steps
        if self.unroll_length is not None and T != self.unroll_length:
            return Rejection("length", f"unroll of {T} steps; the run's unroll_length is {self.unroll_length}")
        if u.obs.keys() != self.rules.keys():
            return Rejection("spec", f"observation fields {sorted(u.obs)}, the env's are {sorted(self.rules)}")
        for k, rule in self.rules.items():
            a = u.obs[k]
            if a.dtype != rule.dtype or a.shape[1:] != rule.shape:
                return Rejection("obs_dtype", f"field {k}: {a.dtype.name}{list(a.shape[1:])}, the env's spec says "
                                              f"{rule.dtype}{list(rule.shape)}")
        a = u.action
        bad_action = self._check_actions(a)
        if bad_action is not None:
            return bad_action
        r = u.reward
        if not np.isfinite(r).all() or float(np.abs(r).max()) > self.max_abs_reward:
            return Rejection("reward_bound", f"|reward| {float(np.abs(r).max()):.3g} exceeds {self.max_abs_reward:.3g}")
        lp = u.behaviour_logp
        top = self.max_logp + self.logp_tolerance
        if not np.isfinite(lp).all() or float(lp.max()) > top or float(lp.min()) < self.min_logp:
            return Rejection("logp_range", f"behaviour log-probabilities span [{float(lp.min()):.3g}, {float(lp.max()):.3g}], "
                                           f"outside [{self.min_logp:.3g}, {self.max_logp:.3g}]")
        if u.behaviour_logits is not None and self.continuous:
            return Rejection("spec", "behaviour logits sent for continuous actions (a Gaussian policy has none)")
        if u.behaviour_logits is not None:
            bad = self._check_logits(u)
            if bad is not None:
                return bad
        if self.check_obs_bounds:
            for group, arrays in (("obs", u.obs), ("final_obs", u.final_obs or {})):
                for k, x in arrays.items():
                    rule = self.rules[k]
                    if rule.low is not None and x.size and ((x < rule.low).any() or (x > rule.high).any()):
                        return Rejection("obs_bounds", f"{group} field {k} has values outside the env's observation bounds")
        return None

    def _check_actions(self, a: np.ndarray) -> Rejection | None:
        if self.continuous:
            if a.ndim != 2 or a.dtype != np.float32 or a.shape[1] != self.n_actions:
                return Rejection("action_range", f"actions {a.dtype.name}{list(a.shape)}; the env's are float32[T, {self.n_actions}]")
            if a.size and float(np.abs(a).max()) > self.max_abs_action:
                return Rejection("action_range", f"|action| {float(np.abs(a).max()):.3g} exceeds {self.max_abs_action:.3g} "
                                                 "(actions are normalised to [-1, 1])")
            return None
        if a.ndim != 1 or a.dtype.kind != "i":
            return Rejection("action_range", f"actions {a.dtype.name}{list(a.shape)}; the env's are int64[T] indices")
        if a.size and (int(a.min()) < 0 or int(a.max()) >= self.n_actions):
            bad = int(a.min()) if int(a.min()) < 0 else int(a.max())
            return Rejection("action_range", f"action {bad} is outside 0..{self.n_actions - 1}")
        return None

    def _check_logits(self, u: Unroll) -> Rejection | None:
        lg = u.behaviour_logits
        if lg.shape[1] != self.n_actions:
            return Rejection("spec", f"behaviour logits for {lg.shape[1]} actions, the env has {self.n_actions}")
        z = lg.astype(np.float64)
        z = z - z.max(axis=1, keepdims=True)
        logp = z[np.arange(u.steps), u.action] - np.log(np.exp(z).sum(axis=1))
        err = float(np.abs(logp - u.behaviour_logp).max())
        if err > self.logp_match_tolerance:
            return Rejection("logp_mismatch", f"behaviour_logp differs from the log-softmax of behaviour_logits by {err:.3g}")
        return None
