"""Frame ids for frame mode (docs/protocol.md, "Frame mode"): Ape-X's n-step transitions
(:mod:`zenrl.actor.nstep`) and R2D2's sequences (:mod:`zenrl.actor.sequences`) number frames
the same way.

An actor numbers the observation frames it records ``0, 1, 2, ...`` and sends each one once; an
observation is named by the id of its frame (``int64[1]``) or, for a stack of k frames (oldest
first, gymnasium's ``FrameStackObservation``), by k ids: slot i of a stack reuses the id of the
previous observation's slot i+1, or of its own slot i+1, where every field's content is equal;
only slots that match nothing are new frames. Equal content is what makes a reuse correct, so
no knowledge of episode boundaries is needed.
"""

from __future__ import annotations

import numpy as np


class FrameNumbering:
    """Ids of the frames of ``num_envs`` envs' observations; ``stack`` 0: each observation is
    one frame, k >= 1: each is a stack of k frames on its first axis."""

    def __init__(self, num_envs: int, stack: int) -> None:
        if stack < 0:
            raise ValueError(f"frame_stack must be >= 0, got {stack}")
        self.k = stack
        self._prev: list[tuple[dict[str, np.ndarray], np.ndarray] | None] = [None] * num_envs
        self._next_id = 0
        self._sent_id = 0
        self._pending: list[dict[str, np.ndarray]] = []
        self._empty: dict[str, np.ndarray] | None = None   # zero frames of each table

    def ids(self, e: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        """int64[max(k, 1)] the frame ids of env ``e``'s observation ``obs[.][e]`` (the next one
        of its sequence of observations); new frames are queued for :meth:`take`."""
        k = self.k
        cur = {f: v[e] for f, v in obs.items()}
        if self._empty is None:
            self._empty = {f: np.zeros((0, *(v.shape[1:] if k else v.shape)), v.dtype) for f, v in cur.items()}
        if not k:
            self._pending.append({f: v.copy() for f, v in cur.items()})
            self._next_id += 1
            return np.array([self._next_id - 1], np.int64)
        prev = self._prev[e]
        ids = np.empty(k, np.int64)
        for i in range(k - 1, -1, -1):
            if i < k - 1:
                if prev is not None and all(np.array_equal(v[i], prev[0][f][i + 1]) for f, v in cur.items()):
                    ids[i] = prev[1][i + 1]
                    continue
                if all(np.array_equal(v[i], v[i + 1]) for v in cur.values()):
                    ids[i] = ids[i + 1]
                    continue
            self._pending.append({f: v[i].copy() for f, v in cur.items()})
            ids[i] = self._next_id
            self._next_id += 1
        self._prev[e] = ({f: v.copy() for f, v in cur.items()}, ids)
        return ids

    def take(self) -> tuple[dict[str, np.ndarray], int]:
        """The frames numbered since the last call, ``{table: [F, *frame shape]}`` (F may be 0),
        and the id of the first: a chunk's ``frames`` and ``frame_base``."""
        base = self._sent_id
        if self._pending:
            frames = {f: np.stack([p[f] for p in self._pending]) for f in self._pending[0]}
        else:
            frames = dict(self._empty or {})
        self._pending = []
        self._sent_id = self._next_id
        return frames, base
