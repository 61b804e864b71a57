"""The IMPALA learner's queue of unrolls, and the batching of B unrolls into time-major tensors.

A Zenoh callback :meth:`UnrollQueue.put` s decoded, checked :class:`~zenrl.common.protocol.Unroll` s;
the training loop :meth:`UnrollQueue.take` s B of them (waiting up to a timeout) and
:func:`batch_unrolls` stacks them. Pure (no Zenoh), thread-safe, unit-tested.

* **Bounded** in unrolls (``max_unrolls``) and decoded bytes (``max_bytes``). A put into a full
  queue never blocks the callback: it evicts the oldest unroll of the source holding the most
  (the putter itself when it is among them), so the freshest data survives (less policy lag).
* **Fair**: one FIFO per source; eviction hits the biggest holder, so a fast actor cannot push
  a slow one's unrolls out, and :meth:`take` draws round-robin across sources (oldest first
  within each), so one actor cannot fill a batch while others wait.
* **Policy lag**: an unroll acted with ``policy_version`` more than ``max_policy_lag`` versions
  behind the learner's :meth:`set_version` is dropped, on put and again on take, and counted.

Counters (``counters``, for the learner's stats): ``queued``, ``taken``, ``stale_dropped``,
``evicted``, ``too_large_dropped``, ``future_version`` (acted with a version newer than the
learner's: kept; after a resume from an older checkpoint the learner resyncs its version).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from zenrl.common.protocol import Unroll


class UnrollQueue:
    """See the module docstring. ``max_unrolls`` >= 1, ``max_bytes`` >= 1, ``max_policy_lag`` >= 0."""

    def __init__(self, max_unrolls: int, max_bytes: int, max_policy_lag: int) -> None:
        if max_unrolls < 1 or max_bytes < 1 or max_policy_lag < 0:
            raise ValueError(f"need max_unrolls >= 1, max_bytes >= 1, max_policy_lag >= 0; got "
                             f"{max_unrolls}, {max_bytes}, {max_policy_lag}")
        self.max_unrolls = max_unrolls
        self.max_bytes = max_bytes
        self.max_policy_lag = max_policy_lag
        self._fifos: dict[str, collections.deque[tuple[Unroll, int]]] = {}  # source -> (unroll, nbytes), oldest first
        self._turn: collections.deque[str] = collections.deque()  # round-robin order of the sources in _fifos
        self._count = 0
        self._bytes = 0
        self._version = 0
        self._cv = threading.Condition()
        self.counters: collections.Counter[str] = collections.Counter()

    def __len__(self) -> int:
        return self._count

    @property
    def nbytes(self) -> int:
        return self._bytes

    def set_version(self, version: int) -> None:
        """The learner's current policy version (staleness is measured against it)."""
        with self._cv:
            self._version = int(version)

    def _stale(self, u: Unroll) -> bool:
        return self._version - u.policy_version > self.max_policy_lag

    def put(self, u: Unroll, source: str | None = None) -> str:
        """Queue ``u`` from ``source`` (default ``u.actor_id``). Returns ``"queued"``,
        ``"stale"`` or ``"too_large"`` (a single unroll over ``max_bytes``); never blocks."""
        source = u.actor_id if source is None else source
        n = u.nbytes
        with self._cv:
            if self._stale(u):
                self.counters["stale_dropped"] += 1
                return "stale"
            if n > self.max_bytes:
                self.counters["too_large_dropped"] += 1
                return "too_large"
            if u.policy_version > self._version:
                self.counters["future_version"] += 1
            while self._count >= self.max_unrolls or self._bytes + n > self.max_bytes:
                self._pop(self._biggest(source))
                self.counters["evicted"] += 1
            fifo = self._fifos.get(source)
            if fifo is None:
                fifo = self._fifos[source] = collections.deque()
                self._turn.append(source)
            fifo.append((u, n))
            self._count += 1
            self._bytes += n
            self.counters["queued"] += 1
            self._cv.notify()
        return "queued"

    def take(self, n: int, timeout: float) -> list[Unroll] | None:
        """``n`` unrolls, round-robin across sources, oldest first within each; waits up to
        ``timeout`` seconds for them, else returns None (nothing is taken)."""
        if not 1 <= n <= self.max_unrolls:
            raise ValueError(f"cannot take {n} unrolls from a queue of at most {self.max_unrolls}")
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                self._drop_stale()
                if self._count >= n:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cv.wait(left)
            out = []
            while len(out) < n:
                source = self._turn[0]
                self._turn.rotate(-1)
                out.append(self._pop(source))
            self.counters["taken"] += n
            return out

    def drop_source(self, source: str) -> int:
        """Forget every unroll of ``source`` (e.g. quarantined); returns how many."""
        with self._cv:
            k = 0
            while source in self._fifos:
                self._pop(source)
                k += 1
            return k

    def sizes(self) -> dict[str, int]:
        """Unrolls held per source."""
        with self._cv:
            return {s: len(f) for s, f in self._fifos.items()}

    # -- under the lock --------------------------------------------------------------------
    def _biggest(self, putter: str) -> str:
        """The source holding the most unrolls; the putter wins ties (it evicts its own)."""
        mine = len(self._fifos.get(putter, ()))
        best = max(self._fifos, key=lambda s: len(self._fifos[s]))
        return putter if mine and mine >= len(self._fifos[best]) else best

    def _pop(self, source: str) -> Unroll:
        fifo = self._fifos[source]
        u, n = fifo.popleft()
        self._count -= 1
        self._bytes -= n
        if not fifo:
            del self._fifos[source]
            self._turn.remove(source)
        return u

    def _drop_stale(self) -> None:
        # a source's versions only grow, so its stale unrolls are at the front of its FIFO
        for source in list(self._fifos):
            while source in self._fifos and self._stale(self._fifos[source][0][0]):
                self._pop(source)
                self.counters["stale_dropped"] += 1


@dataclass(frozen=True)
class UnrollBatch:
    """B unrolls of T steps, time-major tensors. ``obs``: ``{name: [T+1, B, ...]}``;
    ``action`` int64[T, B] (float32[T, B, d]: continuous); ``behaviour_logp``, ``reward`` float32[T, B]; ``terminated``,
    ``truncated`` bool[T, B]; ``final_obs``: ``{name: [K, ...]}``, the final observations of
    the K truncated (not terminated) steps, unroll by unroll; ``final_index`` int64[K]: their
    positions ``t * B + b`` in the flattened [T, B]; ``behaviour_logits`` float32[T, B, A] or
    None (None unless every unroll has them); ``policy_version`` int64[B]."""

    obs: dict[str, torch.Tensor]
    action: torch.Tensor
    behaviour_logp: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    final_obs: dict[str, torch.Tensor]
    final_index: torch.Tensor
    behaviour_logits: torch.Tensor | None
    policy_version: torch.Tensor

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.action.shape[:2])  # type: ignore[return-value]


def batch_unrolls(unrolls: list[Unroll], device: torch.device | str = "cpu") -> UnrollBatch:
    """Stack B >= 1 unrolls of equal T and observation fields into an :class:`UnrollBatch`."""
    if not unrolls:
        raise ValueError("need at least one unroll")
    def form(u: Unroll) -> tuple:
        return u.steps, sorted((k, a.dtype.name, a.shape) for k, a in u.obs.items())

    first = form(unrolls[0])
    names = sorted(unrolls[0].obs)
    for u in unrolls:
        if form(u) != first:
            raise ValueError(f"unrolls differ in steps or observation fields: {form(u)} vs {first}")
    B = len(unrolls)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a).to(device)

    def steps(k: str) -> torch.Tensor:
        return t(np.stack([getattr(u, k) for u in unrolls], axis=1))

    finals = [(b, u) for b, u in enumerate(unrolls) if u.cut.any()]
    index = [t_ * B + b for b, u in finals for t_ in np.flatnonzero(u.cut)]
    final_obs = {k: t(np.concatenate([u.final_obs[k] for _, u in finals]) if finals
                      else np.zeros((0, *unrolls[0].obs[k].shape[1:]), unrolls[0].obs[k].dtype)) for k in names}
    logits = None
    if all(u.behaviour_logits is not None for u in unrolls):
        logits = steps("behaviour_logits")
    return UnrollBatch(obs={k: t(np.stack([u.obs[k] for u in unrolls], axis=1)) for k in names},
                       action=steps("action"), behaviour_logp=steps("behaviour_logp"), reward=steps("reward"),
                       terminated=steps("terminated"), truncated=steps("truncated"), final_obs=final_obs,
                       final_index=t(np.asarray(index, np.int64)), behaviour_logits=logits,
                       policy_version=t(np.array([u.policy_version for u in unrolls], np.int64)))
