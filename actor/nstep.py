"""n-step transitions and their initial priorities for E envs stepped together (Ape-X actors),
built in blocks of K steps.

For a start step ``j`` of env ``e`` the emitted transition holds::

    obs      = s_j                       action = a_j
    reward   = sum_{k=0}^{m-1} gamma^k r_{j+k}      n = m  (m <= n_step)
    next_obs = s_{j+m}                   terminated = whether the episode terminated at j+m-1

``m = n_step`` in mid-episode; when the episode ends within the n steps, ``m`` counts the steps
that remain. With ``cut_non_greedy`` a window also stops before a later step whose action was
not the greedy one (``a != argmax Q`` of the Q values acted on: an exploring or demonstrated
action), bootstrapping from that step's observation (Watkins's cut): the return then measures
the greedy policy's actions, not the behaviour's. ``terminated`` stops bootstrapping
(``discount = gamma ** m * (1 - terminated)``);
``truncated`` bootstraps from ``next_obs``, which is then the episode's final observation.

Each step is only written into preallocated arrays (a few copies); the arithmetic runs once per
block of K steps, vectorized over ``[K, E]``, so its ~50 numpy calls cost per block, not per
step. The builder keeps ``K + n`` rows: a block's last starts need the n steps that follow
them and the observation (and its Q values) after those.

Initial priority: ``|reward + gamma^m (1 - terminated) V(next_obs) - Q(s_j, a_j)|`` with
``V(s) = max_a Q(s, a)`` of the acting network, taken from the forward pass made when the actor
acted on ``s``. A transition whose window ends in a truncation bootstraps from the final
observation, which nobody acted on: for those the caller's ``value_fn`` runs one extra forward.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from zenrl.actor.frame_ids import FrameNumbering


def _max_last(a: np.ndarray) -> np.ndarray:
    """``a.max(-1)``; for a few actions as a loop of elementwise maxima: numpy's reduction over
    a short last axis costs ~30 ns a row (40 us for [21, 64, 2]; the loop ~4 us)."""
    if a.shape[-1] > 16:
        return a.max(-1)
    v = a[..., 0].copy()
    for i in range(1, a.shape[-1]):
        np.maximum(v, a[..., i], out=v)
    return v


@dataclass
class Block:
    """Transitions emitted together: ``data`` fields have leading dim B (``obs*``, ``action``
    int64, ``reward`` float32, ``next_obs*``, ``terminated``/``truncated`` bool, ``n`` uint8);
    ``priorities`` float32[B] (initial, see the module docstring); ``env`` int64[B] the env of
    each."""

    data: dict[str, np.ndarray]
    priorities: np.ndarray
    env: np.ndarray
    #: frame mode: the frames first recorded since the last block (``{obs field: [F, ...]}``),
    #: ids ``frame_base .. frame_base + F - 1``; the obs fields in ``data`` are then frame ids
    frames: dict[str, np.ndarray] | None = None
    frame_base: int = 0

    def __len__(self) -> int:
        return int(self.env.shape[0])


ValueFn = Callable[[dict[str, np.ndarray]], np.ndarray]


class NStepBlocks:
    """Records one batched step per :meth:`add`; every ``block_steps`` steps (once the n steps
    after them are known) :meth:`add` returns a :class:`Block` of ``block_steps * E``
    transitions, otherwise None."""

    def __init__(self, num_envs: int, n_step: int, gamma: float, block_steps: int,
                 frame_stack: int | None = None, cut_non_greedy: bool = False) -> None:
        if n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {n_step}")
        if block_steps < 1:
            raise ValueError(f"block_steps must be >= 1, got {block_steps}")
        self.E, self.n, self.K, self.gamma = num_envs, n_step, block_steps, gamma
        self.rows = block_steps + n_step  # obs rows 0..K+n-1 hold s_t; step rows the same t
        self.t = 0                       # rows filled
        E, R = num_envs, self.rows
        self._obs: dict[str, np.ndarray] | None = None
        self._final: dict[str, np.ndarray] | None = None
        self._act = np.zeros((R, E), np.int64)
        self._rew = np.zeros((R, E), np.float64)
        self._q: np.ndarray | None = None            # Q(s_t, .) [R, E, A]: Q(s, a) and V read at emit
        self._term = np.zeros((R, E), bool)
        self._trunc = np.zeros((R, E), bool)
        self.cut_non_greedy = bool(cut_non_greedy)
        self._off = np.zeros((R, E), bool)           # step t's action was not greedy (cut_non_greedy)
        self._disc = gamma ** np.arange(n_step + 1, dtype=np.float64)
        self._idx: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # frame mode (image envs): observations leave as frame ids, each frame sent once
        if frame_stack is not None and frame_stack < 0:
            raise ValueError(f"frame_stack must be None or >= 0, got {frame_stack}")
        self.frame_stack = frame_stack
        kk = max(frame_stack or 0, 1)
        self._fid = np.zeros((R, E, kk), np.int64)     # frame ids of s_t
        self._ffid = np.zeros((R, E, kk), np.int64)    # frame ids of the final observation
        self._frames = None if frame_stack is None else FrameNumbering(E, frame_stack)

    def add(self, obs: dict[str, np.ndarray], q: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            next_obs: dict[str, np.ndarray], terminated: np.ndarray, truncated: np.ndarray,
            value_fn: ValueFn) -> Block | None:
        """Record step t for every env. ``obs``: s_t (what was acted on, flat arrays [E, ...]);
        ``q``: float[E, A] the Q values it was acted on with; ``actions`` int[E]; ``rewards``
        float[E]; ``next_obs``: s_{t+1} (the final observation where the episode ended; only
        those are read); ``terminated``/``truncated`` bool[E]; ``value_fn`` maps final
        observations [B, ...] to V float[B], called only when a block has truncated windows."""
        t = self.t
        if self._obs is None:
            self._obs = {k: np.zeros((self.rows,) + v.shape, v.dtype) for k, v in obs.items()}
            self._final = {k: np.zeros((self.rows,) + v.shape, v.dtype) for k, v in obs.items()}
            self._q = np.zeros((self.rows,) + q.shape, np.float32)
        for k, v in obs.items():
            self._obs[k][t] = v
        if self.frame_stack is not None:
            for e in range(self.E):
                self._fid[t, e] = self._frame_ids(e, obs)
        self._q[t] = q
        self._act[t] = actions
        if self.cut_non_greedy:
            self._off[t] = actions != q.argmax(1)
        self._rew[t] = rewards
        self._term[t] = terminated
        self._trunc[t] = truncated
        idx = (terminated | truncated).nonzero()[0]  # (flatnonzero and any() cost ~2 us more)
        if idx.size:
            for k, v in next_obs.items():
                self._final[k][t, idx] = v[idx]
            if self.frame_stack is not None:
                for e in idx.tolist():
                    self._ffid[t, e] = self._frame_ids(e, next_obs)
        self.t += 1
        if self.t < self.rows:
            return None
        # s_{K-1+n} and its V are in row K+n-1 = rows-1: every start 0..K-1 is complete
        block = self._emit(self.K, value_fn)
        self._shift(self.K)
        return block

    def _frame_ids(self, e: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Frame ids of env ``e``'s observation ``obs[.][e]``, the next one of its sequence
        (:meth:`FrameNumbering.ids <zenrl.actor.frame_ids.FrameNumbering.ids>`: a stack's slots
        reuse the ids of equal frames, only the others are new)."""
        return self._frames.ids(e, obs)

    def _take_frames(self) -> tuple[dict[str, np.ndarray] | None, int]:
        if self._frames is None:
            return None, 0
        return self._frames.take()

    def flush(self, value_fn: ValueFn) -> Block | None:
        """Emit every start whose n steps and the observation after them are recorded (at
        shutdown); starts nearer the end are dropped."""
        ready = self.t - self.n
        if ready <= 0:
            return None
        block = self._emit(ready, value_fn)
        self._shift(ready)
        return block

    def _shift(self, k: int) -> None:
        keep = slice(k, self.t)
        left = self.t - k
        for arrs in (self._obs, self._final):
            for a in arrs.values():
                a[:left] = a[keep]
        for a in (self._act, self._rew, self._q, self._term, self._trunc, self._off, self._fid, self._ffid):
            a[:left] = a[keep]
        self.t = left

    def _index(self, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """starts int64[K, 1], and start step and env of each flat transition, int64[K * E]."""
        if self._idx is None or self._idx[0].shape[0] != K:
            E = self.E
            self._idx = (np.arange(K)[:, None], np.repeat(np.arange(K), E), np.tile(np.arange(E), K))
        return self._idx

    def _emit(self, K: int, value_fn: ValueFn) -> Block:
        """Starts 0..K-1 of every env (steps j..j+n-1 and row j+n must be recorded, unless the
        episode ended earlier)."""
        n, E = self.n, self.E
        R = np.zeros((K, E))
        m = np.zeros((K, E), np.int64)
        alive = np.ones((K, E), bool)        # window still inside the episode
        going = alive.copy() if self.cut_non_greedy else alive  # and not cut (the same array without cuts)
        k_end = np.zeros((K, E), np.int64)   # step of the window that ended it, where it ended
        starts, j, env = self._index(K)
        done = self._term[:K + n - 1] | self._trunc[:K + n - 1]
        cut = self._off[:K + n - 1] if self.cut_non_greedy else None
        for k in range(n):  # ~6 numpy calls per k: this runs once per block, its cost is per call
            rows = slice(k, k + K)
            if cut is not None and k:
                going &= ~cut[rows]  # stops before step j+k, inside the episode: bootstraps from s_{j+k}
            R += self._disc[k] * np.where(going, self._rew[rows], 0.0)
            m += going
            ends = going & done[rows]
            k_end = np.where(ends, k, k_end)
            alive ^= ends
            if going is not alive:
                going &= ~ends
        ended = ~alive
        end_row = (starts + k_end).ravel()   # row of the ending step
        te_end = self._term[end_row, env].reshape(K, E)
        term = ended & te_end                # an episode that ended and did not terminate was truncated
        trunc = ended & ~te_end
        flat_ended = ended.ravel()
        # next_obs: s_{j+n} in mid-episode (s_{j+m} where cut), the stored final observation where the episode ended
        nxt_row = np.where(flat_ended, end_row, j + (m.ravel() if self.cut_non_greedy else n))
        data: dict[str, np.ndarray] = {}
        e_idx = flat_ended.nonzero()[0]
        if self.frame_stack is not None:
            return self._emit_frames(K, R, m, term, trunc, nxt_row, env, e_idx, flat_ended, value_fn)
        for key, buf in self._obs.items():
            data[key] = buf[:K].reshape((K * E,) + buf.shape[2:]).copy()  # the rows are reused
            nxt = buf[nxt_row, env]
            if e_idx.size:
                nxt[e_idx] = self._final[key][nxt_row[e_idx], env[e_idx]]
            data["next_" + key] = nxt
        prio = self._scalars_and_priorities(data, K, R, m, term, trunc, nxt_row, env, flat_ended, value_fn)
        return Block(data, prio, env.copy())

    def _scalars_and_priorities(self, data: dict[str, np.ndarray], K: int, R: np.ndarray, m: np.ndarray,
                                term: np.ndarray, trunc: np.ndarray, nxt_row: np.ndarray, env: np.ndarray,
                                flat_ended: np.ndarray, value_fn: ValueFn) -> np.ndarray:
        """Adds action, reward, terminated, truncated and n to ``data`` and returns the initial
        priorities float32[K * E]: |R + gamma^m V(s_{j+m}) - Q(s_j, a_j)| with V from the Q rows
        recorded when acting, V(final) from ``value_fn`` where truncated, 0 where terminated."""
        E = self.E
        data["action"] = self._act[:K].ravel().copy()
        data["reward"] = R.ravel().astype(np.float32)
        term_f, trunc_f = term.ravel(), trunc.ravel()
        data["terminated"] = term_f
        data["truncated"] = trunc_f
        m_f = m.ravel()
        data["n"] = m_f.astype(np.uint8)
        A = self._q.shape[2]
        boot = _max_last(self._q).ravel().take(nxt_row * E + env).astype(np.float64)
        boot[flat_ended] = 0.0
        tr_idx = trunc_f.nonzero()[0]
        if tr_idx.size:  # the final observations, from the stored rows (frame mode sends ids instead)
            boot[tr_idx] = value_fn({k: buf[nxt_row[tr_idx], env[tr_idx]] for k, buf in self._final.items()})
        q_sa = self._q[:K].reshape(-1).take(np.arange(0, K * E * A, A) + self._act[:K].ravel())
        return np.abs(R.ravel() + self._disc[m_f] * boot - q_sa).astype(np.float32)

    def _emit_frames(self, K: int, R: np.ndarray, m: np.ndarray, term: np.ndarray, trunc: np.ndarray,
                     nxt_row: np.ndarray, env: np.ndarray, e_idx: np.ndarray, flat_ended: np.ndarray,
                     value_fn: ValueFn) -> Block:
        """The frame-mode tail of :meth:`_emit`: obs fields as frame ids (``int64[B]``, or
        ``int64[B, k]`` for stacks), the block's new frames alongside."""
        E, kk = self.E, self._fid.shape[2]
        obs_ids = self._fid[:K].reshape(K * E, kk)
        nxt_ids = self._fid[nxt_row, env]
        if e_idx.size:
            nxt_ids[e_idx] = self._ffid[nxt_row[e_idx], env[e_idx]]
        squeeze = not self.frame_stack
        data: dict[str, np.ndarray] = {}
        for key in self._obs:
            data[key] = obs_ids[:, 0].copy() if squeeze else obs_ids.copy()
            data["next_" + key] = nxt_ids[:, 0].copy() if squeeze else nxt_ids
        prio = self._scalars_and_priorities(data, K, R, m, term, trunc, nxt_row, env, flat_ended, value_fn)
        frames, base = self._take_frames()
        return Block(data, prio, env.copy(), frames, base)
