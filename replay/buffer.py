"""In-memory prioritized (proportional, Schaul et al. 2016 / Ape-X) replay. Pure numpy, no I/O.

Storage is one preallocated ring array ``[capacity, *shape]`` per spec field. Every inserted
item gets a *key*: the global insertion counter (int64, strictly increasing, never reused).
The item lives at ``slot = key % capacity`` until ``capacity`` newer items evict it (FIFO).
Priority updates name items by key, so an update for an item that has since been overwritten
is recognised (the slot holds a different key) and ignored.

Priorities: a raw priority ``p >= 0`` (typically ``|TD error|``) is stored in the sum tree as
``(p + eps) ** alpha``; sampling probability ``P(i) = (p_i + eps)^alpha / sum_k (p_k + eps)^alpha``.
New items without an explicit priority get :attr:`InMemoryReplay.max_priority`: a high quantile
(``recent_quantile``, 0.99) of the last ``recent_window`` (4096) priorities the learner set through
:meth:`InMemoryReplay.update_priorities` (1.0 before any). Priorities that come with inserted items
(an actor's own estimate) do not move it, and one key counts once per update it is named in: a
single chunk, however high its priorities, cannot pin the priority every later item gets (a
plain running max could be pinned forever by one value).

Removed items (:meth:`InMemoryReplay.remove`: the learner found them poisonous) keep their slot
until it is overwritten but are never sampled again (sum-tree leaf 0, or skipped in uniform mode)
and later priority updates for them are ignored.

Importance-sampling weights ``w_i = (N * P(i)) ** -beta`` are normalised by the **largest
weight in the sampled batch** (i.e. by the smallest sampled probability), as many Ape-X
implementations do, instead of by the global minimum probability. This keeps every weight in
``(0, 1]`` and needs no min-tree; the weights of one batch are a constant factor off those of
the global normalisation, which the learning rate absorbs.

The class is not thread-safe; a caller sharing it between threads must hold a lock.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from zenrl.common.errors import NotReady, SpecMismatch
from zenrl.common.protocol import VIEW_MIN_BYTES, Rows
from zenrl.common.specs import ArraySpec, Spec, spec_nbytes
from zenrl.replay.sumtree import SumTree

logger = logging.getLogger(__name__)

#: Version tag written into :meth:`InMemoryReplay.state_dict`.
STATE_FORMAT = "zenrl.replay.InMemoryReplay/1"
#: ``sample(rows=True)``: a field this large a batch is left as rows, gathered by the reply's
#: encode into its payload (smaller ones cost less gathered at once)
ROWS_MIN_BYTES = VIEW_MIN_BYTES


class ReplayEmpty(NotReady):
    """Sampling was requested from a buffer that holds no items (or only zero priorities)."""


@dataclass(frozen=True)
class SampleBatch:
    """One sampled batch of ``B`` items.

    Attributes:
        keys: ``int64[B]`` keys of the sampled items (pass back to ``update_priorities``).
        probabilities: ``float64[B]`` sampling probability ``P(i)`` of each item.
        weights: ``float32[B]`` importance-sampling weights, max-normalised within the batch.
        data: ``{field: array[B, *shape]}`` gathered copies of the items.
    """

    keys: np.ndarray
    probabilities: np.ndarray
    weights: np.ndarray
    data: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.keys.shape[0])


def _check_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an int, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def _check_float(name: str, value: Any, minimum: float, maximum: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < minimum or v > maximum:
        raise ValueError(f"{name} must be finite and in [{minimum}, {maximum}], got {value!r}")
    return v


def _check_priorities(priorities: Any, n: int, what: str) -> np.ndarray:
    """Validate a ``float64[n]`` array of finite non-negative priorities."""
    p = np.asarray(priorities)
    if p.dtype.kind not in "fiub":
        raise ValueError(f"{what} must be numeric, got dtype {p.dtype}")
    p = p.astype(np.float64, copy=False).reshape(-1) if p.ndim <= 1 else p
    if p.shape != (n,):
        raise ValueError(f"{what} must have shape ({n},), got {np.shape(priorities)}")
    if n:
        lo, hi = p.min(), p.max()  # NaN propagates into both
        if not (lo >= 0.0 and hi < math.inf):
            if not np.all(np.isfinite(p)):
                bad = p[~np.isfinite(p)][0]
                raise ValueError(f"{what} must be finite, got {bad!r}")
            raise ValueError(f"{what} must be >= 0, got {lo!r}")
    return p


class InMemoryReplay:
    """Preallocated ring-buffer prioritized replay over a flat transition spec.

    Args:
        spec: ``{field: ArraySpec}``; items are stored as ``array[capacity, *shape]`` per field.
        capacity: maximum number of items.
        max_bytes: optional cap on item storage; the effective capacity is
            ``min(capacity, max_bytes // bytes_per_item)``. Only the field data counts
            (the 16 B/item of key and priority bookkeeping does not).
        alpha: priority exponent (0 = uniform in effect, 1 = fully proportional).
        uniform: sample uniformly, ignoring priorities (no sum tree is kept).
        eps: added to every raw priority before the exponent, so zero-error items stay
            sampleable.
        seed: seed of the internal generator used when ``sample`` gets no ``rng``.
        recent_window: how many of the latest learner priorities :attr:`max_priority` is taken from.
        recent_quantile: which quantile of them it is (1.0: their max).
    """

    def __init__(
        self,
        spec: Spec,
        capacity: int,
        max_bytes: int | None = None,
        alpha: float = 0.6,
        uniform: bool = False,
        eps: float = 1e-6,
        seed: int | None = None,
        recent_window: int = 4096,
        recent_quantile: float = 0.99,
    ) -> None:
        if not isinstance(spec, Mapping) or len(spec) == 0:
            raise ValueError(f"spec must be a non-empty mapping of field -> ArraySpec, got {spec!r}")
        for name, s in spec.items():
            if not isinstance(name, str) or not name:
                raise ValueError(f"spec field names must be non-empty str, got {name!r}")
            if not isinstance(s, ArraySpec):
                raise ValueError(f"spec[{name!r}] must be an ArraySpec, got {s!r}")
        capacity = _check_int("capacity", capacity, 1)
        if max_bytes is not None:
            max_bytes = _check_int("max_bytes", max_bytes, 0)
        self._alpha = _check_float("alpha", alpha, 0.0)
        if not isinstance(uniform, (bool, np.bool_)):
            raise ValueError(f"uniform must be a bool, got {uniform!r}")
        self._uniform = bool(uniform)
        self._eps = _check_float("eps", eps, 0.0)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
            raise ValueError(f"seed must be an int or None, got {seed!r}")

        self._spec: dict[str, ArraySpec] = dict(spec)
        self._bytes_per_item = spec_nbytes(self._spec)
        self._field_checks = [(k, np.dtype(s.dtype), s.shape) for k, s in self._spec.items()]
        eff = capacity
        if max_bytes is not None and self._bytes_per_item > 0:
            eff = min(capacity, max_bytes // self._bytes_per_item)
            if eff < 1:
                raise ValueError(
                    f"max_bytes={max_bytes} holds no item of {self._bytes_per_item} bytes "
                    f"(effective capacity {eff} < 1)"
                )
        self._capacity = eff
        self._max_bytes = max_bytes

        # np.zeros: pages are only touched (committed) when written.
        self._data: dict[str, np.ndarray] = {
            k: np.zeros((eff, *s.shape), dtype=s.dtype) for k, s in self._spec.items()
        }
        self._keys = np.full(eff, -1, dtype=np.int64)
        self._tree: SumTree | None = None if self._uniform else SumTree(eff)
        self._inserts_total = 0
        self._size = 0
        self._recent = np.ones(_check_int("recent_window", recent_window, 1), dtype=np.float64)
        self._recent_n = 0  # priorities written to the ring so far
        self._quantile = _check_float("recent_quantile", recent_quantile, 0.0, 1.0)
        self._max_priority = 1.0
        self._max_dirty = False
        #: True for a slot whose item was removed (never sampled, its priority updates ignored)
        self._removed = np.zeros(eff, dtype=bool)
        self.stale_updates = 0
        self.removed_total = 0
        self._rng = np.random.default_rng(seed)
        logger.debug(
            "InMemoryReplay: capacity=%d (requested %d), %d B/item, alpha=%s, uniform=%s",
            eff, capacity, self._bytes_per_item, self._alpha, self._uniform,
        )

    # ------------------------------------------------------------------ properties
    @property
    def spec(self) -> dict[str, ArraySpec]:
        """Copy of the item spec."""
        return dict(self._spec)

    @property
    def capacity(self) -> int:
        """Effective capacity (after the byte cap)."""
        return self._capacity

    @property
    def size(self) -> int:
        """Number of items currently stored."""
        return self._size

    def __len__(self) -> int:
        return self._size

    @property
    def bytes_per_item(self) -> int:
        """Bytes of field data per item (``spec_nbytes(spec)``)."""
        return self._bytes_per_item

    @property
    def nbytes(self) -> int:
        """Bytes of field data held by the stored items (``size * bytes_per_item``)."""
        return self._size * self._bytes_per_item

    @property
    def max_priority(self) -> float:
        """The raw priority new items without one get: the ``recent_quantile`` of the last
        ``recent_window`` priorities set by :meth:`update_priorities` (1.0 before any)."""
        if self._max_dirty:
            n = min(self._recent_n, self._recent.shape[0])
            r = self._recent[:n]
            k = min(n - 1, int(math.ceil(self._quantile * n)) - 1) if n else 0
            self._max_priority = float(np.partition(r, k)[k]) if n else 1.0
            self._max_dirty = False
        return self._max_priority

    @property
    def inserts_total(self) -> int:
        """Items ever inserted; also the key the next item will get."""
        return self._inserts_total

    @property
    def priority_mass(self) -> float:
        """The total the sampling probabilities are fractions of: the sum tree's total
        ``sum_i (p_i + eps) ** alpha`` (removed items count 0), or in uniform mode the number of
        stored items not removed (each weighs 1). A learner sampling across replay shards draws
        from each shard in proportion to this (docs/architecture.md)."""
        if self._tree is None:
            return float(self._size - (self.removed_live if self.removed_total else 0))
        return float(self._tree.total)

    @property
    def alpha(self) -> float:
        return self._alpha

    @property
    def uniform(self) -> bool:
        return self._uniform

    @property
    def eps(self) -> float:
        return self._eps

    # ------------------------------------------------------------------ insert
    def _validate_batch(self, batch: Mapping[str, np.ndarray]) -> int:
        if not isinstance(batch, Mapping):
            raise SpecMismatch(f"batch must be a mapping of field -> array, got {type(batch).__name__}")
        if batch.keys() != self._spec.keys():
            missing = sorted(set(self._spec) - set(batch))
            extra = sorted(set(batch) - set(self._spec))
            raise SpecMismatch(f"batch fields differ from the spec: missing {missing}, unexpected {extra}")
        n = -1
        for name, dtype, shape in self._field_checks:
            v = batch[name]
            if not isinstance(v, np.ndarray):
                raise SpecMismatch(f"field {name!r} must be a numpy array, got {type(v).__name__}")
            if v.dtype != dtype:
                raise SpecMismatch(f"field {name!r} has dtype {v.dtype}, spec says {dtype}")
            vs = v.shape
            if vs[1:] != shape or len(vs) != len(shape) + 1:
                raise SpecMismatch(
                    f"field {name!r} has shape {vs}, spec says (B, {', '.join(map(str, shape))})"
                )
            if n < 0:
                n = vs[0]
            elif vs[0] != n:
                raise SpecMismatch(f"field {name!r} has batch size {vs[0]}, other fields have {n}")
        return n

    def insert(self, batch: Mapping[str, np.ndarray], priorities: np.ndarray | None = None) -> np.ndarray:
        """Append a batch (FIFO eviction of the oldest items when full).

        Args:
            batch: ``{field: array[B, *shape]}`` with exactly the spec's fields and dtypes.
            priorities: optional ``float[B]`` raw priorities (finite, >= 0); default: the
                running max priority.

        Returns:
            ``int64[B]`` keys, one per row of the batch. When ``B > capacity`` only the last
            ``capacity`` rows are stored; the keys of the first ``B - capacity`` rows are
            stale from the start.

        Raises:
            SpecMismatch: the batch does not match the spec.
            ValueError: bad priorities.
        """
        n = self._validate_batch(batch)
        p = None if priorities is None else _check_priorities(priorities, n, "priorities")
        start_key = self._inserts_total
        keys = np.arange(start_key, start_key + n, dtype=np.int64)
        if n == 0:
            return keys
        cap = self._capacity
        skip = max(0, n - cap)  # rows that would be overwritten within this very batch
        m = n - skip
        first_key = start_key + skip
        s0 = first_key % cap
        n1 = min(m, cap - s0)  # rows before the wrap
        n2 = m - n1
        for name, arr in self._data.items():
            src = batch[name]
            arr[s0 : s0 + n1] = src[skip : skip + n1]
            if n2:
                arr[:n2] = src[skip + n1 :]
        stored_keys = keys[skip:]
        self._keys[s0 : s0 + n1] = stored_keys[:n1]
        if n2:
            self._keys[:n2] = stored_keys[n1:]

        self._removed[s0 : s0 + n1] = False
        if n2:
            self._removed[:n2] = False
        if self._tree is not None:
            if p is None:
                leaf = np.full(m, self._leaf_value(self.max_priority), dtype=np.float64)
            else:
                leaf = self._leaf_values(p[skip:])
            self._tree.set_range(s0, leaf[:n1])
            if n2:
                self._tree.set_range(0, leaf[n1:])

        self._inserts_total += n
        self._size = min(cap, self._size + n)
        return keys

    def evict_before(self, key: int) -> int:
        """Drop every stored item whose key is below ``key`` ahead of the ring (FIFO order is
        kept: the live items stay one contiguous key range). A frame store calls this when it
        must overwrite a frame that older items still reference. Returns the items dropped."""
        lo = self._inserts_total - self._size
        hi = min(int(key), self._inserts_total)
        if hi <= lo:
            return 0
        cap = self._capacity
        s0, m = lo % cap, hi - lo
        n1 = min(m, cap - s0)
        self._keys[s0 : s0 + n1] = -1
        self._keys[: m - n1] = -1
        if self._tree is not None:
            self._tree.set_range(s0, np.zeros(n1))
            if m > n1:
                self._tree.set_range(0, np.zeros(m - n1))
        self._size -= m
        return m

    def start_at(self, first_key: int) -> None:
        """Make the next insert get key ``first_key`` (an empty buffer only): a replay restored
        from its log keeps the keys its items had, so in-flight priority updates still match."""
        if self._size or self._inserts_total:
            raise ValueError("start_at() needs an empty buffer that has never been inserted into")
        self._inserts_total = _check_int("first_key", first_key, 0)

    def _leaf_value(self, p: float) -> float:
        return float((p + self._eps) ** self._alpha)

    def _leaf_values(self, p: np.ndarray) -> np.ndarray:
        if self._alpha == 1.0:
            return p + self._eps
        return np.power(p + self._eps, self._alpha)

    # ------------------------------------------------------------------ priorities
    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> int:
        """Set the raw priorities of the items named by ``keys``, if they are still stored.

        Args:
            keys: ``int64[K]`` keys from ``insert`` or ``sample`` (duplicates: last wins).
            priorities: ``float[K]`` raw priorities, finite and >= 0.

        Returns:
            How many entries were applied. Keys whose item has been evicted (or that were
            never issued) are ignored and counted in ``self.stale_updates``.
        """
        k = np.asarray(keys)
        if k.dtype.kind not in "iu":
            raise ValueError(f"keys must be integers, got dtype {k.dtype}")
        k = k.astype(np.int64, copy=False).reshape(-1) if k.ndim <= 1 else k
        if k.ndim != 1:
            raise ValueError(f"keys must be 1-D, got shape {np.shape(keys)}")
        p = _check_priorities(priorities, k.shape[0], "priorities")
        if k.shape[0] == 0:
            return 0
        slots = k % self._capacity
        present = self._keys.take(slots) == k
        present &= k >= 0  # empty slots hold -1
        present &= ~self._removed.take(slots)  # a removed item stays removed
        applied = int(np.count_nonzero(present))
        stale = k.shape[0] - applied
        if stale:
            self.stale_updates += stale
            slots = slots[present]
            p = p[present]
        if applied:
            self._remember(p)
            if self._tree is not None:
                self._tree.update(slots, self._leaf_values(p), check=False)
        return applied

    def _remember(self, p: np.ndarray) -> None:
        """Put applied learner priorities in the ring :attr:`max_priority` is taken from."""
        w = self._recent.shape[0]
        if p.shape[0] >= w:
            p = p[-w:]
        i = self._recent_n % w
        n1 = min(p.shape[0], w - i)
        self._recent[i : i + n1] = p[:n1]
        self._recent[: p.shape[0] - n1] = p[n1:]
        self._recent_n += p.shape[0]
        self._max_dirty = True

    def remove(self, keys: np.ndarray) -> np.ndarray:
        """Never sample the items named by ``keys`` again (the learner found them poisonous): their
        leaf is set to 0 (in uniform mode sampling skips them) and later priority updates for them
        are ignored; they leave the buffer when the ring overwrites their slot.

        Args:
            keys: ``int64[K]`` keys from ``sample`` (duplicates allowed).

        Returns:
            ``bool[K]``: which entries named an item stored (and not yet removed) at the call;
            the others (evicted, never issued, already removed) changed nothing.
        """
        k = np.asarray(keys)
        if k.dtype.kind not in "iu" or k.ndim != 1:
            raise ValueError(f"keys must be a 1-D integer array, got {k.dtype}{list(k.shape)}")
        k = k.astype(np.int64, copy=False)
        hit = np.zeros(k.shape[0], dtype=bool)
        if not k.shape[0]:
            return hit
        slots = k % self._capacity
        hit = (k >= 0) & (self._keys.take(slots) == k) & ~self._removed.take(slots)
        # a key named twice counts once
        _, first = np.unique(k, return_index=True)
        once = np.zeros(k.shape[0], dtype=bool)
        once[first] = True
        hit &= once
        s = slots[hit]
        if s.shape[0]:
            self._removed[s] = True
            if self._tree is not None:
                self._tree.update(s, np.zeros(s.shape[0]), check=False)
            self.removed_total += int(s.shape[0])
        return hit

    @property
    def removed_live(self) -> int:
        """Removed items still holding a slot."""
        return int(np.count_nonzero(self._removed))

    # ------------------------------------------------------------------ sampling
    def sample(
        self,
        batch_size: int,
        beta: float,
        rng: np.random.Generator | None = None,
        out: Mapping[str, np.ndarray] | None = None,
        rows: bool = False,
    ) -> SampleBatch:
        """Draw ``batch_size`` items (with replacement).

        Prioritized mode: stratified proportional sampling; ``[0, total)`` is split into
        ``batch_size`` equal segments and one point is drawn uniformly in each, then all are
        located with one batched tree descent.

        Args:
            batch_size: ``B >= 1``.
            beta: IS exponent in ``[0, inf)`` (usually annealed from ~0.4 to 1).
            rng: generator to draw from; default the buffer's own (seeded) generator.
            out: optional preallocated ``{field: array[B, *shape]}`` (C-contiguous, spec
                dtype) to gather into; ``SampleBatch.data`` then holds these very arrays.
                Reusing buffers avoids page-faulting fresh memory on every call, which
                dominates for large (image) items.
            rows: (without ``out``) fields of at least ``ROWS_MIN_BYTES`` a batch come back
                as :class:`~zenrl.common.protocol.Rows` of the storage, to be gathered by
                the reply's encode into its payload; the caller holds off inserts until then.

        Raises:
            ReplayEmpty: the buffer is empty (or every stored priority is 0 with ``eps=0``).
            SpecMismatch: ``out`` does not match the spec and batch size.
        """
        b = _check_int("batch_size", batch_size, 1)
        beta = _check_float("beta", beta, 0.0)
        if out is not None:
            self._check_out(out, b)
        if self._size == 0:
            raise ReplayEmpty("cannot sample from an empty replay buffer")
        g = self._rng if rng is None else rng
        n = self._size
        if self._tree is None:
            first = (self._inserts_total - n) % self._capacity  # oldest stored item's slot
            slots = (first + g.integers(0, n, size=b, dtype=np.int64)) % self._capacity
            if self.removed_total:
                slots = self._redraw_removed(slots, first, n, g)
            probs = np.full(b, 1.0 / n, dtype=np.float64)
            weights = np.ones(b, dtype=np.float32)
        else:
            total = self._tree.total
            if not total > 0.0:
                raise ReplayEmpty("cannot sample: every stored priority is 0 (use eps > 0)")
            seg = total / b
            targets = (np.arange(b, dtype=np.float64) + g.random(b)) * seg
            slots = self._tree.find_prefix_sum(targets)
            leaf = self._tree.values_at(slots)
            probs = leaf / total
            # w_i = (N P_i)^-beta / max_j (N P_j)^-beta = (min_j P_j / P_i)^beta
            if beta == 0.0:
                weights = np.ones(b, dtype=np.float32)
            else:
                weights = np.power(leaf.min() / leaf, beta).astype(np.float32)
        if out is None:
            # ndarray.take(axis=0) is several times faster than fancy indexing for item rows
            # with more than one element; for 1-D fields fancy indexing is marginally faster.
            data = {
                name: (Rows(arr, slots, (b, *arr.shape[1:])) if rows and arr.ndim > 1 and arr[0].nbytes * b >= ROWS_MIN_BYTES
                       else arr.take(slots, axis=0, mode="clip") if arr.ndim > 1 else arr[slots])
                for name, arr in self._data.items()
            }
        else:
            # mode="clip" (indices are in range anyway): with the default mode="raise",
            # take() buffers the output, which is several times slower.
            data = {}
            for name, arr in self._data.items():
                data[name] = arr.take(slots, axis=0, out=out[name], mode="clip")
        return SampleBatch(keys=self._keys[slots], probabilities=probs, weights=weights, data=data)

    def _redraw_removed(self, slots: np.ndarray, first: int, n: int, g: np.random.Generator) -> np.ndarray:
        """Uniform mode: draw again the slots that hold removed items (uniform over the rest)."""
        dead = self._removed.take(slots)
        if not dead.any():
            return slots
        live = (first + np.flatnonzero(~self._removed.take((first + np.arange(n)) % self._capacity))) % self._capacity
        if not live.shape[0]:
            raise ReplayEmpty("cannot sample: every stored item was removed")
        slots = slots.copy()
        slots[dead] = live[g.integers(0, live.shape[0], size=int(dead.sum()))]
        return slots

    def _check_out(self, out: Mapping[str, np.ndarray], b: int) -> None:
        if not isinstance(out, Mapping) or out.keys() != self._spec.keys():
            raise SpecMismatch(f"out must have exactly the spec's fields {sorted(self._spec)}")
        for name, dtype, shape in self._field_checks:
            o = out[name]
            if (
                not isinstance(o, np.ndarray)
                or o.dtype != dtype
                or o.shape != (b, *shape)
                or not o.flags.c_contiguous
                or not o.flags.writeable
            ):
                raise SpecMismatch(
                    f"out[{name!r}] must be a writeable C-contiguous {dtype} array of shape "
                    f"{(b, *shape)}, got {getattr(o, 'dtype', type(o).__name__)} "
                    f"{getattr(o, 'shape', '')}"
                )

    def priorities_of(self, keys: np.ndarray) -> np.ndarray:
        """Stored tree values ``(p + eps) ** alpha`` for keys (``nan`` for stale keys)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1)
        out = np.full(k.shape[0], np.nan)
        present = (k >= 0) & (self._keys[k % self._capacity] == k)
        if self._tree is None:
            out[present] = np.where(self._removed[k[present] % self._capacity], 0.0, 1.0)
        else:
            out[present] = self._tree.get(k[present] % self._capacity)
        return out

    def raw_priorities(self) -> tuple[np.ndarray, np.ndarray]:
        """``(keys int64[N], raw priorities float64[N])`` of every stored item (inverting
        ``(p + eps) ** alpha``; all ones in uniform mode), for priority snapshots."""
        keys = self._keys[self._keys >= 0]
        if self._tree is None:
            return keys, np.ones(keys.shape[0])
        leaves = self._tree.get(keys % self._capacity)
        raw = leaves if self._alpha == 0 else np.power(leaves, 1.0 / self._alpha) - self._eps
        return keys, np.maximum(raw, 0.0)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to restore this buffer, as numpy arrays and Python scalars/str.

        Only the ``size`` filled slots are saved. Values are ``np.ndarray``, ``int``,
        ``float``, ``str``, ``bool`` or nested dicts of those (no pickle needed).
        """
        n = self._size
        if n != min(self._inserts_total, self._capacity):
            raise ValueError("a buffer that evicted items ahead of the ring (evict_before) has no state_dict")
        spec = {
            name: {"shape": np.asarray(s.shape, dtype=np.int64), "dtype": s.dtype}
            for name, s in self._spec.items()
        }
        bg = self._rng.bit_generator
        state: dict[str, Any] = {
            "format": STATE_FORMAT,
            "spec": spec,
            "capacity": int(self._capacity),
            "alpha": float(self._alpha),
            "uniform": bool(self._uniform),
            "eps": float(self._eps),
            "inserts_total": int(self._inserts_total),
            "size": int(n),
            "max_priority": float(self.max_priority),
            "recent": self._recent[: min(self._recent_n, self._recent.shape[0])].copy(),
            "removed": self._removed[:n].copy(),
            "stale_updates": int(self.stale_updates),
            "keys": self._keys[:n].copy(),
            "leaves": (
                self._tree.leaves[:n].copy() if self._tree is not None else np.zeros(0, np.float64)
            ),
            "data": {name: arr[:n].copy() for name, arr in self._data.items()},
            "rng": {
                "bit_generator": type(bg).__name__,
                "state_json": json.dumps(bg.state, default=lambda o: o.tolist()),
            },
        }
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore from :meth:`state_dict`. The spec, capacity, alpha, eps and mode must match.

        Raises:
            SpecMismatch: the saved spec differs from this buffer's spec.
            ValueError: other incompatibility or a malformed state.
        """
        if not isinstance(state, Mapping):
            raise ValueError(f"state must be a mapping, got {type(state).__name__}")
        fmt = state.get("format")
        if fmt != STATE_FORMAT:
            raise ValueError(f"unknown replay state format {fmt!r}, expected {STATE_FORMAT!r}")
        saved_spec = {}
        for name, s in dict(state["spec"]).items():
            saved_spec[name] = ArraySpec(tuple(int(x) for x in np.asarray(s["shape"]).reshape(-1)), str(s["dtype"]))
        if saved_spec != self._spec:
            raise SpecMismatch(f"saved replay spec {saved_spec} differs from this buffer's spec {self._spec}")
        for name in ("capacity", "alpha", "uniform", "eps"):
            mine = getattr(self, name)
            if state[name] != mine:
                raise ValueError(f"saved replay {name}={state[name]!r} differs from this buffer's {name}={mine!r}")
        n = int(state["size"])
        inserts = int(state["inserts_total"])
        if not 0 <= n <= self._capacity or n != min(inserts, self._capacity):
            raise ValueError(f"saved replay size={n} inconsistent with inserts_total={inserts}, capacity={self._capacity}")
        keys = np.asarray(state["keys"])
        if keys.shape != (n,) or keys.dtype != np.int64:
            raise ValueError(f"saved replay keys must be int64[{n}], got {keys.dtype}{list(keys.shape)}")
        data = dict(state["data"])
        for name, s in self._spec.items():
            a = np.asarray(data[name])
            if a.shape != (n, *s.shape) or a.dtype.name != s.dtype:
                raise SpecMismatch(f"saved field {name!r} is {a.dtype.name}{list(a.shape)}, expected {s.dtype}{[n, *s.shape]}")
        leaves = np.asarray(state["leaves"], dtype=np.float64)
        if self._tree is not None and leaves.shape != (n,):
            raise ValueError(f"saved replay leaves must be float64[{n}], got shape {leaves.shape}")
        rng_state = dict(state["rng"])
        bg_cls = getattr(np.random, str(rng_state["bit_generator"]), None)
        if bg_cls is None or not isinstance(bg_cls, type) or not issubclass(bg_cls, np.random.BitGenerator):
            raise ValueError(f"unknown bit generator {rng_state['bit_generator']!r}")
        bg = bg_cls()
        bg.state = json.loads(rng_state["state_json"])

        # All checks passed: mutate.
        for name, arr in self._data.items():
            arr[:n] = data[name]
            arr[n:] = 0
        self._keys[:] = -1
        self._keys[:n] = keys
        if self._tree is not None:
            full = np.zeros(self._capacity, dtype=np.float64)
            full[:n] = leaves
            self._tree.set_leaves(full)
        self._inserts_total = inserts
        self._size = n
        self._max_priority = float(state["max_priority"])
        self._max_dirty = False
        recent = np.asarray(state.get("recent", np.zeros(0)), dtype=np.float64).reshape(-1)[-self._recent.shape[0]:]
        self._recent[: recent.shape[0]] = recent
        self._recent_n = recent.shape[0]
        self._removed[:] = False
        removed = state.get("removed")
        if removed is not None:
            self._removed[:n] = np.asarray(removed, dtype=bool).reshape(-1)[:n]
        self.stale_updates = int(state["stale_updates"])
        self._rng = np.random.Generator(bg)
