"""What an env gives its actor, checked before any of it leaves the actor.

The services check every message against the env's spec (``replay.check_semantics``, the IMPALA
learner's unroll checks) because an actor may be hostile; they reject a chunk as a whole and
quarantine a source that keeps sending bad ones. An honest actor whose env misbehaves (a NaN
reward now and then, an observation a little outside its declared ``Box``, a reward larger than
the run allows) would lose whole chunks, then all of its output for a minute, with the reason only
in the service's log. :class:`EnvGuard` looks at each batched step first, with the same rules:

* a reward that is not one number (a size-1 array is taken as its number) or whose magnitude
  exceeds the run's bound stops the actor with :class:`~zenrl.common.errors.EnvOutputError`
  (every step would repeat it; the launcher stops the run with the message, which names the
  setting to change);
* a step whose reward or observation holds NaN or Inf is cut: the episode ends there as
  truncated, with reward 0 and the observation before the step as its last (the bad step's data
  are dropped), and the env is reset; a reset that gives NaN or Inf is retried (3 times, then
  :class:`~zenrl.common.errors.EnvOutputError`);
* a finite observation outside the env's finite bounds, where the run's services check them, is
  clipped to them;
* observations are put in the dtype their space names where nothing is lost (ints for a float
  ``Box``); one of another shape, a missing or extra ``Dict`` key, or floats for a uint8 image or
  a ``Discrete`` index stops the actor (``zenrl run`` checks the first reset the same way before
  any process starts).

Each is counted (``env_steps_cut``, ``env_obs_clipped``, ``env_resets_retried`` in the actor's
stats) and logged at most once per 30 s per kind, naming the env and the field. The fast path is
a handful of whole-batch numpy comparisons per step; all of the above happens only when one
fails.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from zenrl.common.errors import EnvOutputError
from zenrl.common.metrics import RejectCounter
from zenrl.common.specs import SEP, obs_rules_from_space

log = logging.getLogger(__name__)

#: a reset that gives NaN or Inf is tried this many times more before the actor stops
RESET_RETRIES = 3
#: each kind of problem is logged at most once per this many seconds (the rest counted)
LOG_EVERY_S = 30.0


@dataclass(frozen=True)
class EnvLimits:
    """What the run's services accept from an env: ``max_abs_reward`` (None: no bound) and the
    setting that holds it (named in the error), ``check_bounds``: observations must lie in the
    env's finite ``Box`` bounds."""

    max_abs_reward: float | None = None
    reward_setting: str = ""
    check_bounds: bool = False
    #: the setting that turns the observation-bound checks off (named in the clip's warning)
    bounds_setting: str = ""

    @classmethod
    def of(cls, cfg: Any) -> "EnvLimits":
        """The limits of a run (:class:`~zenrl.common.config.RunConfig`): the replay's checks for
        Ape-X and R2D2, the IMPALA learner's for IMPALA; A3C's gradients carry no env data."""
        if cfg.algo in ("apex", "r2d2"):
            r = cfg.replay
            if not r.check_semantics:
                return cls()
            return cls(r.max_abs_reward, "replay.max_abs_reward", r.check_obs_bounds, "replay.check_obs_bounds")
        if cfg.algo == "impala":
            return cls(cfg.impala.max_abs_reward, "impala.max_abs_reward", cfg.impala.check_obs_bounds,
                       "impala.check_obs_bounds")
        return cls()


def reward_number(r: Any, env_id: str) -> float:
    """An env's reward as a float: a number, or an array of one element; anything else is an
    :class:`EnvOutputError` naming what the env gave."""
    try:
        return float(r)
    except (TypeError, ValueError):
        pass
    try:
        a = np.asarray(r)
    except (TypeError, ValueError):
        a = None
    if a is None or a.dtype.kind not in "biuf" or a.size != 1:
        what = f"an array of shape {a.shape}" if a is not None and a.dtype.kind in "biuf" else f"a {type(r).__name__}"
        raise EnvOutputError(f"env {env_id} returned a reward that is {what}, not one number "
                             "(gymnasium's step returns one float reward)") from None
    return float(a.reshape(()))


#: the dtype kinds cast, without loss of meaning, to a field of each kind (float: bool and any
#: number; int (a Discrete index): bool and ints; uint8 images: bool only, 0/1)
_CASTS_TO = {"f": "biuf", "i": "biu", "u": "b"}
#: how a message names a dtype kind (a float64 observation reaches the check as float32 already)
_KINDS = {"f": "floats", "i": "ints", "u": "unsigned ints", "b": "bools", "c": "complex numbers", "O": "Python objects",
          "U": "strings", "S": "bytes", "V": "records", "M": "datetimes", "m": "timedeltas"}


class _Field:
    """One flat observation field's check: ``low``/``high`` as arrays of one item's shape (NaN
    and Inf fail them: unbounded elements get the dtype's largest finite values), or None for a
    field nothing can be wrong with (uint8 in [0, 255], or an unbounded int field)."""

    def __init__(self, name: str, dtype: str, shape: tuple[int, ...], low: np.ndarray | None, high: np.ndarray | None,
                 check_bounds: bool) -> None:
        self.name = name
        self.key = name[len("obs" + SEP):] if name.startswith("obs" + SEP) else None
        self.floating = np.dtype(dtype).kind == "f"
        self.bounded = check_bounds and low is not None
        if self.floating:
            big = float(np.finfo(dtype).max)
            lo64 = np.broadcast_to(low, shape).astype(np.float64) if self.bounded else np.full(shape, -np.inf)
            hi64 = np.broadcast_to(high, shape).astype(np.float64) if self.bounded else np.full(shape, np.inf)
            lo, hi = np.clip(lo64, -big, big).astype(dtype), np.clip(hi64, -big, big).astype(dtype)
            # a finite bound that rounding to the dtype moved inward is widened by one step, so that
            # no value inside the float64 bound is clipped; an infinite one stays at the dtype's largest
            # finite value, so that Inf fails the check as NaN does
            inward_lo, inward_hi = np.isfinite(lo64) & (lo > lo64), np.isfinite(hi64) & (hi < hi64)
            with np.errstate(over="ignore"):  # the step past the largest value is computed, not taken
                self.low = np.where(inward_lo, np.nextafter(lo, np.array(-np.inf, dtype)), lo).astype(dtype)
                self.high = np.where(inward_hi, np.nextafter(hi, np.array(np.inf, dtype)), hi).astype(dtype)
        elif self.bounded:
            self.low, self.high = np.broadcast_to(low, shape).astype(np.float64), np.broadcast_to(high, shape).astype(np.float64)
        else:
            self.low = self.high = None
        self._tiled: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def active(self) -> bool:
        return self.low is not None

    def within(self, a: np.ndarray) -> bool:
        """Every row of the batch ``a`` [E, ...] inside the bounds (NaN and Inf fail). The bounds
        are tiled to E rows once: broadcasting [E, D] against [D] runs numpy's inner loop once per
        row, many times slower than one contiguous comparison at small D."""
        tiled = self._tiled.get(len(a))
        if tiled is None:
            tiled = self._tiled[len(a)] = (np.ascontiguousarray(np.broadcast_to(self.low, a.shape)),
                                           np.ascontiguousarray(np.broadcast_to(self.high, a.shape)))
        # NaN fails both comparisons; count_nonzero is the cheapest whole-array test of a few values
        return np.count_nonzero(a >= tiled[0]) + np.count_nonzero(a <= tiled[1]) == 2 * a.size

    def rows_ok(self, a: np.ndarray) -> np.ndarray:
        """bool[E]: the rows of ``a`` [E, ...] inside the bounds (and finite)."""
        ok = (a >= self.low) & (a <= self.high)
        return ok.reshape(len(a), -1).all(axis=1)

    def fix(self, value: Any) -> tuple[Any, str | None]:
        """One observation's value of this field -> (clipped value, what was wrong) or, when it
        holds NaN or Inf, (None, what)."""
        a = np.asarray(value)
        if self.floating and not np.isfinite(a).all():
            return None, f"observation {self.name} holds NaN or Inf"
        below, above = a < self.low, a > self.high
        if not (below.any() or above.any()):
            return value, None
        i = int(np.flatnonzero((below | above).reshape(-1))[0])
        low_side = bool(below.reshape(-1)[i])
        where = "below" if low_side else "above"
        v, b = a.reshape(-1)[i], (self.low if low_side else self.high).reshape(-1)[i]
        fixed = np.clip(a, self.low, self.high).astype(a.dtype)
        return fixed, f"observation {self.name}[{i}] = {float(v):.6g} is {where} the env's bound {float(b):.6g}"


class EnvGuard:
    """The checks of one actor's envs (see the module docstring): ``env_id`` for the messages,
    the envs' ``observation_space`` (as zenrl ships it), the run's :class:`EnvLimits`."""

    def __init__(self, env_id: str, observation_space: Any, limits: EnvLimits | None = None) -> None:
        self.env_id = env_id
        self.limits = limits or EnvLimits()
        rules = obs_rules_from_space(observation_space)
        #: every flat field's dtype and per-item shape, as the env's space (zenrl's wire form) says
        self.expected = {k: (np.dtype(r.dtype), tuple(r.shape)) for k, r in rules.items()}
        self.fields = [f for f in (_Field(k, r.dtype, r.shape, r.low, r.high, self.limits.check_bounds)
                                   for k, r in rules.items()) if f.active]
        self.dict_obs = any(k != "obs" for k in rules)
        self.bound = self.limits.max_abs_reward
        #: rewards inside this range need no look (the run's bound, or the largest finite floats)
        big = float(np.finfo(np.float64).max)
        self.reward_range = (-big, big) if self.bound is None else (-self.bound, self.bound)
        #: counts by kind (``steps_cut``, ``obs_clipped``, ``resets_retried``), each logged at most
        #: once per LOG_EVERY_S with the count of the rest
        self.fixes = RejectCounter(log, f"output of env {env_id}", LOG_EVERY_S, verb="fixed")

    # -- rewards ---------------------------------------------------------------------------------
    def reward(self, r: Any) -> float:
        """One env step's reward as a float (:func:`reward_number`); one beyond the run's bound
        stops the actor (NaN and Inf are left to :meth:`screen`, which cuts the step)."""
        x = r if type(r) is float else reward_number(r, self.env_id)
        if self.bound is not None and math.isfinite(x) and abs(x) > self.bound:
            raise EnvOutputError(f"env {self.env_id} gave a reward of {x:.6g}, beyond {self.limits.reward_setting} = "
                                 f"{self.bound:.6g}: the run's checks would refuse it. Raise "
                                 f"{self.limits.reward_setting} above the largest reward (n-step sum for Ape-X) "
                                 "the env gives")
        return x

    # -- observations ----------------------------------------------------------------------------
    def conform(self, flat: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The flat batch with each field in the dtype its space names: numbers of another
        kind that the dtype holds (ints for a float ``Box``, any int for a ``Discrete``) are cast;
        a field missing, extra, of another shape, or of a dtype that would lose what it holds
        (floats for a uint8 image, floats for a ``Discrete`` index) is an
        :class:`EnvOutputError`: the env does not give what its observation_space says."""
        for name, (dt, shape) in self.expected.items():
            a = flat.get(name)
            if a is None:
                raise EnvOutputError(f"env {self.env_id} gave no observation {name}; its observation_space has it")
            if a.shape[1:] != shape:
                raise EnvOutputError(f"env {self.env_id} gave observation {name} of shape {tuple(a.shape[1:])}; its "
                                     f"observation_space says {shape}")
            if a.dtype != dt:
                if a.dtype.kind not in _CASTS_TO.get(dt.kind, ""):
                    raise EnvOutputError(f"env {self.env_id} gave observation {name} as {_KINDS[a.dtype.kind]}; its "
                                         f"observation_space says {dt.name} (zenrl's form of it)")
                flat[name] = a.astype(dt)
        if len(flat) != len(self.expected):
            extra = sorted(set(flat) - set(self.expected))
            raise EnvOutputError(f"env {self.env_id} gave observation {extra[0]}, which its observation_space does not have")
        return flat

    def clean(self, flat: Mapping[str, np.ndarray]) -> bool:
        """The per-step fast path: True when no observation of the flat batch needs a look (one
        sum per unbounded float field: NaN or Inf make it non-finite; two comparisons per bounded
        field). False may be a false alarm (a sum that overflows): :meth:`bad_rows` decides."""
        for f in self.fields:
            a = flat[f.name]
            if f.bounded or not f.floating:
                if not f.within(a):
                    return False
            elif not math.isfinite(float(a.sum())):
                return False
        return True

    def bad_rows(self, flat: Mapping[str, np.ndarray], rewards: np.ndarray | None = None) -> np.ndarray | None:
        """None when every row of the flat batch ``flat`` (and of ``rewards``) passes; else the
        indices of the rows that do not."""
        ok = None
        for f in self.fields:
            r = f.rows_ok(flat[f.name])
            ok = r if ok is None else ok & r
        if rewards is not None:
            fin = np.isfinite(rewards)
            ok = fin if ok is None else ok & fin
        if ok is None or ok.all():
            return None
        return np.flatnonzero(~ok)

    def fix(self, obs: Any) -> tuple[Any, list[str], bool]:
        """One observation -> (the observation with out-of-bounds values clipped, what was wrong,
        whether it holds NaN or Inf: then it cannot be fixed)."""
        notes: list[str] = []
        if not self.dict_obs:
            f = self.fields[0] if self.fields else None
            if f is None:
                return obs, notes, False
            v, why = f.fix(obs)
            if why:
                notes.append(why)
            return (obs if v is None else v), notes, v is None
        out = _copy_tree(obs)
        broken = False
        for f in self.fields:
            path = f.key.split(SEP)
            parent = out
            for p in path[:-1]:
                parent = parent[p]
            v, why = f.fix(parent[path[-1]])
            if v is None:  # what cannot be fixed is named first
                broken = True
                notes.insert(0, why)
            else:
                if why:
                    notes.append(why)
                parent[path[-1]] = v
        return out, notes, broken

    def note(self, kind: str, what: str) -> None:
        """Count a problem of ``kind`` (``steps_cut``, ``obs_clipped``, ``resets_retried``) and log
        ``what`` (at most once per :data:`LOG_EVERY_S` per kind, the rest counted)."""
        self.fixes.reject(kind, what)

    def values(self) -> dict[str, int]:
        c = self.fixes.counts
        return {f"env_{k}": c[k] for k in ("steps_cut", "obs_clipped", "resets_retried")}


def _copy_tree(obs: Any) -> Any:
    if isinstance(obs, Mapping):
        return {k: _copy_tree(v) for k, v in obs.items()}
    return obs
