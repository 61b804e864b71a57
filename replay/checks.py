"""What a transition chunk must *mean* before the replay stores it, and who gets quarantined for
sending chunks that do not. Pure (no zenoh, no env), unit-tested without a network.

The protocol layer already rejects what is malformed (bad containers, dtypes, shapes, NaN/Inf).
A well-formed chunk can still wreck a run: an action index the network does not have crashes the
learner on ``gather`` (and stays in the replay at high priority, so the restarted learner dies
again); a finite reward of 3e38 makes the loss ``inf``. :class:`ChunkChecker` holds the run's
env spec (observation fields with their dtypes and finite ``Box`` bounds, the number of actions,
``n_step``) and the configured bounds on rewards and priorities, and names the first rule a
chunk breaks; :class:`SequenceChecker` does the same for R2D2's chunks, whose items are
sequences. :class:`~zenrl.common.quarantine.Quarantine` (shared with the IMPALA learner) drops a
source's traffic for a while once it keeps breaking rules.
"""

from __future__ import annotations

from typing import Any, Container, Mapping

import numpy as np

from zenrl.common.quarantine import Quarantine
from zenrl.common.specs import ObsRule, Rejection, obs_rules_from_space

__all__ = ["Checker", "ChunkChecker", "ObsRule", "Quarantine", "Rejection", "SequenceChecker", "obs_rules_from_space"]

#: Fields every Ape-X chunk carries besides the observations (dtype of one item, shape ()).
SCALAR_FIELDS = {"action": "int64", "reward": "float32", "n": "uint8", "terminated": "bool"}
#: Fields an Ape-X chunk may carry besides those (shape ()).
OPTIONAL_FIELDS = {"truncated": "bool"}


#: Elements per block of tiled observation bounds (see ChunkChecker).
BOUNDS_BLOCK_ELEMENTS = 4096


def _as_bound(b: np.ndarray, dtype: str, direction: int) -> np.ndarray:
    """A bound (float64, +-inf where unbounded) in the data's dtype, flattened, rounded outward
    so that no value inside the float64 bound is rejected."""
    b = b.reshape(-1)
    if np.dtype(dtype).kind == "f":
        out = b.astype(dtype)
        widen = (out < b) if direction > 0 else (out > b)
        out[widen] = np.nextafter(out[widen], np.inf if direction > 0 else -np.inf)
        return out
    info = np.iinfo(dtype)
    return np.clip(np.floor(b) if direction > 0 else np.ceil(b), info.min, info.max).astype(dtype)


def _tiled_bounds(rules: Mapping[str, ObsRule], check_obs_bounds: bool) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    """The bounded fields as ``(name, rows R, low, high)`` with one item's bounds tiled R times,
    so that a batch is compared as contiguous blocks of R items (broadcasting [B, D] against [D]
    runs numpy's inner loop once per row: ~70x slower for CartPole's D = 4)."""
    out = []
    for k, r in rules.items():
        if r.low is None or not check_obs_bounds:
            continue
        d = max(1, int(np.prod(r.shape, dtype=np.int64)))
        rows = max(1, BOUNDS_BLOCK_ELEMENTS // d)
        out.append((k, rows, np.tile(_as_bound(r.low, r.dtype, -1), rows), np.tile(_as_bound(r.high, r.dtype, 1), rows)))
    return out


def _bounds_rejection(k: str, a: np.ndarray, rows: int, low: np.ndarray, high: np.ndarray) -> Rejection | None:
    """``a`` [N, ...] (N items of field ``k``) against the tiled bounds of :func:`_tiled_bounds`."""
    flat = a.reshape(-1)
    whole = (a.shape[0] // rows) * low.shape[0]
    rest = flat[whole:]
    if whole:  # elementwise min/max across the blocks, then one comparison of a block
        blocks = flat[:whole].reshape(-1, low.shape[0])
        if (blocks.min(axis=0) < low).any() or (blocks.max(axis=0) > high).any():
            return Rejection("obs_bounds", f"field {k} has values outside the env's observation bounds")
    if (rest < low[:rest.shape[0]]).any() or (rest > high[:rest.shape[0]]).any():
        return Rejection("obs_bounds", f"field {k} has values outside the env's observation bounds")
    return None


def _required_fields(required: Mapping[str, tuple[np.dtype, tuple[int, ...]]], obs_rules: Mapping[str, Any],
                     data: Mapping[str, np.ndarray]) -> Rejection | None:
    """The first field of ``required`` ({name: (dtype, shape of one item)}) that ``data`` lacks
    or carries with another dtype or shape (``obs_dtype`` for an observation field)."""
    for k, (dt, shape) in required.items():
        a = data.get(k)
        if a is None:
            return Rejection("spec", f"field {k} is missing")
        if a.dtype != dt or a.shape[1:] != shape:
            return Rejection("obs_dtype" if k in obs_rules else "spec",
                             f"field {k}: {a.dtype.name}{list(a.shape[1:])}, the run's spec says {dt.name}{list(shape)}")
    return None


def frame_shapes(rule: ObsRule, frame_stack: int | None) -> list[tuple[int, ...]]:
    """The shapes one frame of an observation field may have in frame mode (``frame_stack``:
    the run's ``actor.frame_stack``; None: unknown, either form)."""
    whole, one = tuple(rule.shape), tuple(rule.shape[1:])
    if frame_stack is None:
        return [whole, one] if rule.shape else [whole]
    return [one] if frame_stack else [whole]



def missing_or_misshapen(data: Mapping[str, np.ndarray], fields: Mapping[str, tuple[np.dtype, tuple[int, ...]]],
                         skip: Container[str]) -> Rejection | None:
    """The first of ``fields`` ({name: (dtype, per-item shape)}, those in ``skip`` left out: frame
    fields, checked as ids) that ``data`` lacks or holds with another dtype or per-item shape."""
    for k, (dt, shape) in fields.items():
        if k in skip:
            continue
        a = data.get(k)
        if a is None:
            return Rejection("spec", f"field {k} is missing")
        if a.dtype != dt or a.shape[1:] != shape:
            return Rejection("spec", f"field {k}: {a.dtype.name}{list(a.shape[1:])}, expected {dt.name}{list(shape)}")
    return None

class ChunkChecker:
    """Checks one chunk's ``data`` (flat ``{name: array[B, ...]}``) and ``priorities``
    (float32[B] or None) against the run's env spec and bounds.

    ``obs_rules``: the observation fields (``obs`` or ``obs/<key>``); ``next_obs*`` follow the
    same rules. ``n_actions``: actions must be in ``0..n_actions-1``; ``n_step``: ``n`` in
    ``1..n_step``; ``max_abs_reward``: ``|reward|`` bound; ``max_priority``: priority bound
    (priorities are already known finite and non-negative); ``check_obs_bounds`` False skips
    the observation bounds (dtypes and shapes are still checked)."""

    def __init__(self, obs_rules: Mapping[str, ObsRule], n_actions: int, n_step: int,
                 max_abs_reward: float, max_priority: float, check_obs_bounds: bool = True,
                 frame_stack: int | None = None) -> None:
        if n_actions < 1 or n_step < 1:
            raise ValueError(f"n_actions and n_step must be >= 1, got {n_actions} and {n_step}")
        self.n_actions = int(n_actions)
        self.n_step = int(n_step)
        self.max_abs_reward = float(max_abs_reward)
        self.max_priority = float(max_priority)
        self.rules: dict[str, ObsRule] = {}
        for name, r in obs_rules.items():
            self.rules[name] = r
            self.rules["next_" + name] = r
        # np.dtype objects, compared by identity-or-equality: ``dtype.name`` costs ~1.6 us a call
        self.required = {**{k: (np.dtype(r.dtype), r.shape) for k, r in self.rules.items()},
                         **{k: (np.dtype(dt), ()) for k, dt in SCALAR_FIELDS.items()}}
        self.optional = {k: (np.dtype(dt), ()) for k, dt in OPTIONAL_FIELDS.items()}
        self._bounded = _tiled_bounds(self.rules, check_obs_bounds)
        self._n_actions = np.uint64(self.n_actions)
        self._n_step = np.uint8(min(self.n_step, 255))
        #: frame mode: k frames per observation (the run's ``actor.frame_stack``; 0: whole
        #: observations are frames), None: either layout the env allows
        self.frame_stack = frame_stack

    def packed_shapes(self) -> dict[str, tuple[tuple[int, ...], ...]]:
        """The arrays of a chunk that may travel compressed (the env's uint8 fields), with the
        shapes one row may have: ``{"data.<field>" or "frames.<table>": (item shapes)}``; see
        :class:`~zenrl.common.protocol.DecodeLimits`."""
        out: dict[str, tuple[tuple[int, ...], ...]] = {}
        for k, (dt, shape) in {**self.required, **self.optional}.items():
            if dt == np.uint8:
                out[f"data.{k}"] = (tuple(shape),)
        for k, r in self.rules.items():
            if not k.startswith("next_") and np.dtype(r.dtype) == np.uint8:
                out[f"frames.{k}"] = tuple(dict.fromkeys(frame_shapes(r, self.frame_stack)))
        return out

    def check_frame_fields(self, data: Mapping[str, np.ndarray], frames: Mapping[str, np.ndarray]) -> Rejection | None:
        """A frame-mode chunk's layout against the env's spec, exactly: one frame table per
        observation field of the env, every observation field ``X`` and ``next_X`` present as
        int64 ids ``[B]`` (whole observations) or ``[B, k]`` (stacks of ``k =
        actor.frame_stack`` frames), the scalar fields and ``truncated``, nothing else. So the
        storage built from the first chunk that passes is the one the env spec defines."""
        obs = {k: r for k, r in self.rules.items() if not k.startswith("next_")}
        if frames.keys() != obs.keys():
            return Rejection("spec", f"frame tables {sorted(frames)[:8]} differ from the env's observation fields {sorted(obs)}")
        refs = set()
        for k, rule in obs.items():
            a = frames[k]
            one = tuple(a.shape[1:])
            if a.dtype != np.dtype(rule.dtype) or one not in frame_shapes(rule, self.frame_stack):
                return Rejection("fields", f"frames of {k}: {a.dtype.name}{list(one)}, the env's {k} is "
                                           f"{rule.dtype}{list(rule.shape)} (frame_stack {self.frame_stack})")
            stack = 0 if one == tuple(rule.shape) else int(rule.shape[0])
            for f in (k, "next_" + k):
                ids = data.get(f)
                if ids is None:
                    return Rejection("spec", f"field {f} (frame ids) is missing")
                if ids.dtype != np.int64 or ids.shape[1:] != ((stack,) if stack else ()):
                    return Rejection("spec", f"frame ids {f}: {ids.dtype.name}{list(ids.shape[1:])} per item, the env's "
                                             f"layout needs int64{[stack] if stack else []}")
                refs.add(f)
        bad = missing_or_misshapen(data, {**self.required, **self.optional}, self.rules)
        if bad is not None:
            return bad
        extra = sorted(set(data) - refs - set(self.required) - set(self.optional))
        if extra:
            return Rejection("spec", f"field {extra[0][:128]} is not part of a frame-mode Ape-X transition")
        return None

    @classmethod
    def from_spaces(cls, observation_space: Any, action_space: Any, n_step: int, max_abs_reward: float,
                    max_priority: float, check_obs_bounds: bool = True, frame_stack: int | None = None) -> "ChunkChecker":
        import gymnasium as gym

        if not isinstance(action_space, gym.spaces.Discrete):
            raise ValueError(f"zenrl's replay checks need a Discrete action space, got {action_space}")
        return cls(obs_rules_from_space(observation_space), int(action_space.n), n_step, max_abs_reward, max_priority,
                   check_obs_bounds, frame_stack)

    def check(self, data: Mapping[str, np.ndarray], priorities: np.ndarray | None,
              fields_checked: bool = False) -> Rejection | None:
        """``None`` if the chunk may be stored, else the first rule it breaks. Each rule is one or
        two whole-array numpy operations (per-call overhead dominates at CartPole's sizes).
        ``fields_checked``: the caller already knows the field names, dtypes and shapes match
        (e.g. they match a storage allocated from a chunk that passed this check); only values
        are checked then."""
        if not fields_checked:
            bad = self.check_fields(data)
            if bad is not None:
                return bad
        bad = self.check_scalars(data, priorities)
        if bad is not None:
            return bad
        return self._check_bounds(data)

    def check_scalars(self, data: Mapping[str, np.ndarray], priorities: np.ndarray | None) -> Rejection | None:
        """The action, ``n``, reward and priority rules alone (frame-mode chunks, whose
        observations are frame ids, are checked with this and :meth:`check_frames`)."""
        for k, (dt, _shape) in self.required.items():
            if k in SCALAR_FIELDS and (k not in data or data[k].dtype != dt or data[k].ndim != 1):
                return Rejection("fields", f"field {k} must be {dt.name}[B]")
        act = data["action"]
        # int64 read as uint64: a negative action becomes huge, so one max covers both ends
        if act.view(np.uint64).max() >= self._n_actions:
            bad = int(act.max()) if int(act.max()) >= self.n_actions else int(act.min())
            return Rejection("action_range", f"action {bad} is outside 0..{self.n_actions - 1}")
        n = data["n"]
        # uint8: n - 1 wraps 0 to 255, so one max covers both ends
        if (n - np.uint8(1)).max() >= self._n_step:
            bad = int(n.min()) if int(n.min()) < 1 else int(n.max())
            return Rejection("n_range", f"n {bad} is outside 1..{self.n_step}")
        r = data["reward"]
        m = float(np.abs(r).max())
        if m > self.max_abs_reward:
            return Rejection("reward_bound", f"|reward| {m:.3g} exceeds replay.max_abs_reward {self.max_abs_reward:.3g}")
        if priorities is not None:
            p = float(priorities.max())
            if p > self.max_priority:
                return Rejection("priority_bound", f"priority {p:.3g} exceeds replay.max_priority {self.max_priority:.3g}")
        return None

    def check_frames(self, frames: Mapping[str, np.ndarray]) -> Rejection | None:
        """Frame-mode frames (``{obs field: array[F, ...]}``): each table is an observation
        field of the env, of its dtype, one observation (or one frame of a stacked one) per row,
        inside the field's bounds."""
        return check_frame_tables(self.rules, frames)

    def _check_bounds(self, data: Mapping[str, np.ndarray]) -> Rejection | None:
        for k, rows, low, high in self._bounded:
            bad = _bounds_rejection(k, data[k], rows, low, high)
            if bad is not None:
                return bad
        return None

    def check_fields(self, data: Mapping[str, np.ndarray]) -> Rejection | None:
        """Field names, dtypes and per-item shapes against the env's spec."""
        bad = _required_fields(self.required, self.rules, data)
        if bad is not None:
            return bad
        if len(data) != len(self.required):
            for k, a in data.items():
                if k in self.required:
                    continue
                want = self.optional.get(k)
                if want is None:
                    return Rejection("spec", f"field {k} is not part of an Ape-X transition")
                if a.dtype != want[0] or a.shape[1:] != want[1]:
                    return Rejection("spec", f"field {k}: {a.dtype.name}{list(a.shape[1:])}, expected {want[0].name}{list(want[1])}")
        return None


#: R2D2 sequence fields with one value per step (shape [m] per item), and their dtypes
SEQUENCE_STEP_FIELDS = {"action": "int64", "reward": "float32", "terminated": "bool", "truncated": "bool",
                        "mask": "bool"}
#: the recurrent state a sequence starts from (shape [H] per item, float32)
SEQUENCE_STATE_FIELDS = ("h", "c")
#: default bound on |c|, the LSTM's cell state (|h| <= 1 always): |c| grows by at most 1 a step
DEFAULT_MAX_ABS_CELL = 1e6


def check_frame_tables(rules: Mapping[str, ObsRule], frames: Mapping[str, np.ndarray]) -> Rejection | None:
    """Frame-mode frames (``{obs field: array[F, ...]}``) against the observation fields'
    ``rules`` (``next_*`` rules are not tables): each table an observation field of the env, of
    its dtype, one observation (or one frame of a stacked one) per row, inside the field's bounds."""
    for k, a in frames.items():
        rule = rules.get(k)
        if rule is None or k.startswith("next_"):
            return Rejection("fields", f"frame table {k} is not an observation field of the env ({sorted(r for r in rules if not r.startswith('next_'))})")
        if a.dtype != np.dtype(rule.dtype) or a.shape[1:] not in (tuple(rule.shape), tuple(rule.shape[1:])):
            return Rejection("fields", f"frames of {k}: {a.dtype.name}{list(a.shape[1:])}, the env's {k} is "
                                       f"{rule.dtype}{list(rule.shape)} (or one frame of it)")
        if rule.low is not None and a.size and a.shape[1:] == tuple(rule.shape):
            low, high = rule.low.reshape(rule.shape), rule.high.reshape(rule.shape)
            if (a < low).any() or (a > high).any():
                return Rejection("obs_bounds", f"frames of {k} have values outside the env's observation bounds")
    return None


class SequenceChecker:
    """Checks one chunk of R2D2 sequences (one item = one sequence of m steps, as cut by
    :mod:`zenrl.actor.sequences`) against the run's env spec and bounds, with the interface of
    :class:`ChunkChecker` (``check``, ``check_fields``, ``check_scalars``, ``check_frames``).

    Fields of one item: ``obs`` / ``obs/<key>`` [m+1, ...] of the env's dtype and shape;
    ``action`` int64[m], ``reward`` float32[m], ``terminated``/``truncated``/``mask`` bool[m];
    ``first`` bool[]; ``h``, ``c`` float32[H]. Meaning: every step's action in
    ``0..n_actions-1`` (padding too: the learner gathers every step), ``mask`` a prefix of
    length >= 1 (the valid steps), an episode's end (terminated or truncated) only at a
    sequence's last valid step, ``|reward| <= max_abs_reward``, ``|h| <= 1`` (an LSTM's output)
    and ``|c| <= max_abs_cell``, the observations s_0..s_len (s_len the one after the last valid
    step; zeros pad the rest) inside the env's finite ``Box`` bounds, priority bound.

    Frame mode (image envs, :mod:`zenrl.actor.sequences`): ``obs/<key>`` are int64 frame ids
    ``[m+1]`` per item (each observation one frame) or ``[m+1, k]`` (stacks of ``k =
    actor.frame_stack``), the frames themselves checked as Ape-X's (:func:`check_frame_tables`).
    ``frame_stack`` None accepts either layout the env allows."""

    def __init__(self, obs_rules: Mapping[str, ObsRule], n_actions: int, length: int, lstm_size: int,
                 max_abs_reward: float, max_priority: float, check_obs_bounds: bool = True,
                 max_abs_cell: float = DEFAULT_MAX_ABS_CELL, frame_stack: int | None = None) -> None:
        if n_actions < 1 or length < 1 or lstm_size < 1:
            raise ValueError(f"n_actions, length and lstm_size must be >= 1, got {n_actions}, {length}, {lstm_size}")
        self.n_actions, self.length, self.lstm_size = int(n_actions), int(length), int(lstm_size)
        self.max_abs_reward, self.max_priority, self.max_abs_cell = float(max_abs_reward), float(max_priority), float(max_abs_cell)
        self.rules: dict[str, ObsRule] = dict(obs_rules)
        m = self.length
        self.required = {**{k: (np.dtype(r.dtype), (m + 1, *r.shape)) for k, r in self.rules.items()},
                         **{k: (np.dtype(dt), (m,)) for k, dt in SEQUENCE_STEP_FIELDS.items()},
                         "first": (np.dtype("bool"), ()),
                         **{k: (np.dtype("float32"), (self.lstm_size,)) for k in SEQUENCE_STATE_FIELDS}}
        # bounds of one observation; checked on the valid observations gathered as [N, ...]
        self._bounded = _tiled_bounds(self.rules, check_obs_bounds)
        self._n_actions = np.uint64(self.n_actions)
        self.frame_stack = frame_stack

    @classmethod
    def from_spaces(cls, observation_space: Any, action_space: Any, length: int, lstm_size: int,
                    max_abs_reward: float, max_priority: float, check_obs_bounds: bool = True,
                    frame_stack: int | None = None) -> "SequenceChecker":
        import gymnasium as gym

        if not isinstance(action_space, gym.spaces.Discrete):
            raise ValueError(f"zenrl's replay checks need a Discrete action space, got {action_space}")
        return cls(obs_rules_from_space(observation_space), int(action_space.n), length, lstm_size, max_abs_reward,
                   max_priority, check_obs_bounds, frame_stack=frame_stack)

    def check(self, data: Mapping[str, np.ndarray], priorities: np.ndarray | None,
              fields_checked: bool = False) -> Rejection | None:
        """``None`` if the chunk may be stored, else the first rule it breaks (``fields_checked``:
        as for :meth:`ChunkChecker.check`)."""
        if not fields_checked:
            bad = self.check_fields(data)
            if bad is not None:
                return bad
        return self.check_scalars(data, priorities) or self._check_bounds(data)

    def check_fields(self, data: Mapping[str, np.ndarray]) -> Rejection | None:
        """Field names, dtypes and per-item shapes against the env's spec, m and H."""
        bad = _required_fields(self.required, self.rules, data)
        if bad is not None:
            return bad
        for k in data:
            if k not in self.required:
                return Rejection("spec", f"field {k} is not part of an R2D2 sequence")
        return None

    def check_scalars(self, data: Mapping[str, np.ndarray], priorities: np.ndarray | None) -> Rejection | None:
        """Every rule but the observation bounds."""
        act = data["action"]
        # int64 read as uint64: a negative action becomes huge, so one max covers both ends
        if act.size and act.view(np.uint64).max() >= self._n_actions:
            bad = int(act.max()) if int(act.max()) >= self.n_actions else int(act.min())
            return Rejection("action_range", f"action {bad} is outside 0..{self.n_actions - 1}")
        mask = data["mask"]
        if not mask[:, 0].all() or (mask[:, 1:] & ~mask[:, :-1]).any():
            return Rejection("mask", "a sequence's mask must be a prefix of valid steps, at least one long")
        done = (data["terminated"] | data["truncated"]) & mask
        last = mask & ~np.concatenate([mask[:, 1:], np.zeros_like(mask[:, :1])], axis=1)   # the last valid step
        if (done & ~last).any():
            return Rejection("done_inside", "an episode ends before a sequence's last valid step")
        m = float(np.abs(data["reward"]).max())
        if m > self.max_abs_reward:
            return Rejection("reward_bound", f"|reward| {m:.3g} exceeds replay.max_abs_reward {self.max_abs_reward:.3g}")
        h, c = float(np.abs(data["h"]).max()), float(np.abs(data["c"]).max())
        if h > 1.0 or c > self.max_abs_cell:
            return Rejection("state_bound", f"|h| {h:.3g} > 1 or |c| {c:.3g} > {self.max_abs_cell:.3g}: not an LSTM's state")
        if priorities is not None:
            p = float(priorities.max())
            if p > self.max_priority:
                return Rejection("priority_bound", f"priority {p:.3g} exceeds replay.max_priority {self.max_priority:.3g}")
        return None

    def check_frames(self, frames: Mapping[str, np.ndarray]) -> Rejection | None:
        """Frame-mode frames: see :func:`check_frame_tables`."""
        return check_frame_tables(self.rules, frames)

    def check_frame_fields(self, data: Mapping[str, np.ndarray], frames: Mapping[str, np.ndarray]) -> Rejection | None:
        """A frame-mode chunk's layout against the env's spec, exactly: one frame table per
        observation field, each observation field as int64 ids ``[m+1]`` (whole observations)
        or ``[m+1, k]`` (stacks of ``k`` frames) per item, the other fields of a sequence, nothing
        else."""
        if frames.keys() != self.rules.keys():
            return Rejection("spec", f"frame tables {sorted(frames)[:8]} differ from the env's observation fields {sorted(self.rules)}")
        m1 = self.length + 1
        for k, rule in self.rules.items():
            a = frames[k]
            one = tuple(a.shape[1:])
            if a.dtype != np.dtype(rule.dtype) or one not in frame_shapes(rule, self.frame_stack):
                return Rejection("fields", f"frames of {k}: {a.dtype.name}{list(one)}, the env's {k} is "
                                           f"{rule.dtype}{list(rule.shape)} (frame_stack {self.frame_stack})")
            want = (m1,) if one == tuple(rule.shape) else (m1, int(rule.shape[0]))
            ids = data.get(k)
            if ids is None:
                return Rejection("spec", f"field {k} (frame ids) is missing")
            if ids.dtype != np.int64 or ids.shape[1:] != want:
                return Rejection("spec", f"frame ids {k}: {ids.dtype.name}{list(ids.shape[1:])} per item, the env's "
                                         f"layout needs int64{list(want)}")
        bad = missing_or_misshapen(data, self.required, self.rules)
        if bad is not None:
            return bad
        extra = sorted(set(data) - set(self.required))
        if extra:
            return Rejection("spec", f"field {extra[0][:128]} is not part of a frame-mode R2D2 sequence")
        return None

    def packed_shapes(self) -> dict[str, tuple[tuple[int, ...], ...]]:
        """The env's uint8 fields of a sequence, with the shape of one item, and the frame
        tables of frame mode with the shapes one frame may have (see
        :meth:`ChunkChecker.packed_shapes`)."""
        out = {f"data.{k}": (tuple(shape),) for k, (dt, shape) in self.required.items() if dt == np.uint8}
        for k, r in self.rules.items():
            if np.dtype(r.dtype) == np.uint8:
                out[f"frames.{k}"] = tuple(dict.fromkeys(frame_shapes(r, self.frame_stack)))
        return out

    def _check_bounds(self, data: Mapping[str, np.ndarray]) -> Rejection | None:
        if not self._bounded:
            return None
        valid = np.concatenate([data["mask"][:, :1], data["mask"]], axis=1)   # s_0..s_len: [B, m+1]
        for k, rows, low, high in self._bounded:
            bad = _bounds_rejection(k, data[k][valid], rows, low, high)
            if bad is not None:
                return bad
        return None


#: what the replay checks chunks with (one for the run, chosen by its algo: replay/service.py)
Checker = ChunkChecker | SequenceChecker
