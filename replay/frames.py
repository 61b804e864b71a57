"""Prioritized replay that stores every observation frame once (image envs). Pure numpy, no I/O.

An image transition names its observations by *frame ids* instead of carrying them: an actor
numbers the frames it sends (``0, 1, 2, ...``, one id per recorded observation step, shared by
every frame table), ships each new frame once, and a transition's ``obs/X`` / ``next_obs/X``
are ids into table ``obs/X``: ``int64[B]`` (the item is one frame) or ``int64[B, k]`` (the item
is a stack ``[k, *frame_shape]`` of k frames, oldest first, stacked on a new leading axis as
gymnasium's ``FrameStackObservation`` does). With n-step returns ``next_obs`` is simply the id
of the observation the same actor recorded n steps later, and neighbouring stacks share k-1 ids,
so a frame costs its bytes once whatever the n and the stack.

Storage:

* one ring ``[frame_capacity, *frame_shape]`` per frame table, filled in arrival order: frame
  *global key* ``g`` lives at slot ``g % frame_capacity``;
* an :class:`InMemoryReplay` of the transitions, whose fields are the non-frame columns plus,
  per frame field, the global keys of its frames (``int64[k]``: 8 bytes per frame reference).

A chunk may reference frames of the same actor's earlier chunks (the n steps after a chunk's
last starts arrive with the next chunk). Each actor's recent chunks are remembered as ``(first
id, count, first global key)``; an id that resolves to no stored frame (the chunk that carried it
was lost, rejected or evicted, or the actor restarted: its ids went backwards) drops the
transition, counted in :attr:`FrameReplay.unresolved`, never a wrong frame.

Eviction stays FIFO and exact: before a frame slot is overwritten, every transition that
references any frame being overwritten is evicted together with all older transitions
(``InMemoryReplay.evict_before``), found through ``last_ref[slot]``, the newest transition key
referencing each frame. So a stored transition's frames are always present. When frames arrive
faster than ``frames_per_item`` per transition, the frame ring, not ``capacity``, bounds the
number of stored transitions.

The class is not thread-safe; a caller sharing it between threads must hold a lock.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from zenrl.common.errors import SpecMismatch
from zenrl.common.protocol import Rows, frame_table
from zenrl.common.specs import ArraySpec, Spec, spec_nbytes
from zenrl.replay.buffer import InMemoryReplay, SampleBatch, _check_priorities

logger = logging.getLogger(__name__)

#: Prefix of the transition columns that hold the global frame keys of a frame field.
GKEY_PREFIX = "frame_keys/"
#: Chunks remembered per actor for references into earlier chunks.
MAX_HISTORY = 256


@dataclass
class _History:
    bases: deque
    counts: deque
    gbases: deque
    end: int = 0  # one past the last frame id received


@dataclass(frozen=True)
class FrameChunk:
    """One actor's chunk for :meth:`FrameReplay.insert_many` (the arguments of ``insert``)."""
    stream: str
    frame_base: int
    frames: Mapping[str, np.ndarray]
    batch: Mapping[str, np.ndarray]
    refs: Mapping[str, np.ndarray]
    priorities: np.ndarray | None = None
    #: ``{field: (min id, max id)}`` of ``refs``, exactly, where the caller has them already
    #: (:meth:`~zenrl.common.protocol.TransitionBatch.frame_id_bounds`); None: found here
    bounds: Mapping[str, tuple[int, int]] | None = None


@dataclass(frozen=True)
class InsertResult:
    keys: np.ndarray  #: int64[B'] keys of the stored transitions
    dropped: int      #: transitions dropped because a frame id did not resolve


class FrameReplay:
    """Transitions in an :class:`InMemoryReplay`, their observation frames in rings, stored once.

    Args:
        item_spec: the non-frame columns ``{field: ArraySpec}`` (action, reward, ...).
        frame_spec: ``{table: ArraySpec(frame_shape, dtype)}`` one frame of each table.
        ref_stack: ``{field: k}`` per frame field: ``0`` = one frame (ids ``int64[B]``),
            ``k >= 1`` = a stack of k frames (ids ``int64[B, k]``), or a tuple: the shape of one
            item's ids (``(m+1,)`` or ``(m+1, k)`` for an R2D2 sequence of m steps: its
            observations, each one frame or a stack of k); each field reads table
            :func:`~zenrl.common.protocol.frame_table` (field); a sampled item has the frames
            laid out as its ids (``[*id shape, *frame shape]``).
        capacity: most transitions stored.
        frames_per_item: frame ring size per transition slot (``frame_capacity = ceil(capacity
            * frames_per_item)``); an actor sends about ``1 + 1 / episode length`` frames per
            transition.
        max_bytes: optional cap on all storage (frames and transitions); scales capacity down.
        alpha, uniform, eps, seed: as :class:`InMemoryReplay`.
    """

    def __init__(self, item_spec: Spec, frame_spec: Spec, ref_stack: Mapping[str, int | tuple[int, ...]], capacity: int,
                 frames_per_item: float = 1.1, max_bytes: int | None = None, alpha: float = 0.6,
                 uniform: bool = False, eps: float = 1e-6, seed: int | None = None) -> None:
        if not frame_spec:
            raise ValueError("frame_spec must name at least one frame table")
        if not isinstance(frames_per_item, (int, float)) or not 0.0 < frames_per_item < math.inf:
            raise ValueError(f"frames_per_item must be a positive number, got {frames_per_item!r}")
        if not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an int >= 1, got {capacity!r}")
        self._frame_spec = {k: v for k, v in frame_spec.items()}
        self._ref_stack: dict[str, int | tuple[int, ...]] = {}
        #: the shape of one item's ids per frame field (``()``: one frame)
        self._ref_shape: dict[str, tuple[int, ...]] = {}
        for f, k in ref_stack.items():
            if frame_table(f) not in self._frame_spec:
                raise ValueError(f"frame field {f!r} reads table {frame_table(f)!r}, which is not in frame_spec")
            if isinstance(k, tuple):
                if not k or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in k):
                    raise ValueError(f"ref_stack[{f!r}] as a shape must be a non-empty tuple of ints >= 1, got {k!r}")
                self._ref_shape[f] = k
            elif isinstance(k, bool) or not isinstance(k, int) or k < 0:
                raise ValueError(f"ref_stack[{f!r}] must be an int >= 0 or a shape tuple, got {k!r}")
            else:
                self._ref_shape[f] = (k,) if k else ()
            self._ref_stack[f] = k
        clash = set(item_spec) & set(ref_stack)
        if clash:
            raise ValueError(f"fields {sorted(clash)} are both columns and frame fields")
        inner_spec = dict(item_spec)
        for f, shape in self._ref_shape.items():
            inner_spec[GKEY_PREFIX + f] = ArraySpec((max(math.prod(shape), 1),), "int64")
        frame_bytes = spec_nbytes(self._frame_spec)
        if max_bytes is not None:
            per_item = spec_nbytes(inner_spec) + frames_per_item * frame_bytes
            fit = int(max_bytes // per_item)
            if fit < 1:
                raise ValueError(f"max_bytes={max_bytes} holds no transition of ~{per_item:.0f} bytes")
            capacity = min(capacity, fit)
        self._inner = InMemoryReplay(inner_spec, capacity, alpha=alpha, uniform=uniform, eps=eps, seed=seed)
        # the columns a chunk brings itself (its frame ids become the gkey columns): what
        # _precheck's fast path compares, without building the gkey stand-ins
        self._col_keys = frozenset(item_spec)
        self._col_checks = [(k, np.dtype(s.dtype), s.shape) for k, s in item_spec.items()]
        # np.dtype objects: comparing them costs far less than ``dtype.name``
        self._frame_checks = [(t, np.dtype(s.dtype), s) for t, s in self._frame_spec.items()]
        self._ref_width = {f: max(math.prod(shape), 1) for f, shape in self._ref_shape.items()}
        self._fcap = max(1, math.ceil(capacity * frames_per_item))
        self._frames = {k: np.zeros((self._fcap, *s.shape), s.dtype) for k, s in self._frame_spec.items()}
        self._last_ref = np.full(self._fcap, -1, np.int64)
        self._frames_total = 0
        self._frame_bytes = frame_bytes
        self._streams: dict[str, _History] = {}
        self.unresolved = 0
        self.evicted_by_frames = 0
        logger.debug("FrameReplay: %d transitions, %d frames of %d B", capacity, self._fcap, frame_bytes)

    # ------------------------------------------------------------------ properties
    @property
    def capacity(self) -> int:
        return self._inner.capacity

    @property
    def frame_capacity(self) -> int:
        return self._fcap

    @property
    def size(self) -> int:
        return self._inner.size

    def __len__(self) -> int:
        return self._inner.size

    @property
    def inserts_total(self) -> int:
        return self._inner.inserts_total

    @property
    def priority_mass(self) -> float:
        """:attr:`InMemoryReplay.priority_mass` of the transitions."""
        return self._inner.priority_mass

    @property
    def frames_total(self) -> int:
        return self._frames_total

    @property
    def frames_stored(self) -> int:
        return min(self._frames_total, self._fcap)

    @property
    def max_priority(self) -> float:
        return self._inner.max_priority

    @property
    def stale_updates(self) -> int:
        return self._inner.stale_updates

    @property
    def spec(self) -> dict[str, ArraySpec]:
        """Spec of a sampled item (frame fields as the learner sees them)."""
        out = {k: v for k, v in self._inner.spec.items() if not k.startswith(GKEY_PREFIX)}
        for f, shape in self._ref_shape.items():
            s = self._frame_spec[frame_table(f)]
            out[f] = ArraySpec((*shape, *s.shape), s.dtype)
        return out

    @property
    def bytes_per_item(self) -> int:
        """Allocated bytes per transition slot: the columns plus the frame rings' share."""
        return self._inner.bytes_per_item + math.ceil(self._fcap * self._frame_bytes / self._inner.capacity)

    @property
    def nbytes(self) -> int:
        """Bytes held by the stored transitions and frames."""
        return self._inner.nbytes + self.frames_stored * self._frame_bytes

    @property
    def wire_spec(self) -> tuple[dict[str, ArraySpec], dict[str, ArraySpec], dict[str, int | tuple[int, ...]]]:
        """``(item_spec, frame_spec, ref_stack)`` this store was built with."""
        item = {k: v for k, v in self._inner.spec.items() if not k.startswith(GKEY_PREFIX)}
        return item, dict(self._frame_spec), dict(self._ref_stack)

    # ------------------------------------------------------------------ insert
    def check(self, frames: Mapping[str, np.ndarray], refs: Mapping[str, np.ndarray]) -> int:
        """Validate frames and references against the store; returns the frame count F."""
        if frames.keys() != self._frame_spec.keys():
            raise SpecMismatch(f"frame tables {sorted(frames)} differ from the replay's {sorted(self._frame_spec)}")
        n_f = -1
        for t, dt, s in self._frame_checks:
            a = frames[t]
            if a.dtype != dt or a.shape[1:] != s.shape:
                raise SpecMismatch(f"frames {t}: {a.dtype.name}{list(a.shape[1:])} differs from the replay's {s.dtype}{list(s.shape)}")
            if n_f < 0:
                n_f = a.shape[0]
            elif a.shape[0] != n_f:
                raise SpecMismatch(f"frames {t}: {a.shape[0]} frames, other tables have {n_f}")
        if refs.keys() != self._ref_stack.keys():
            raise SpecMismatch(f"frame fields {sorted(refs)} differ from the replay's {sorted(self._ref_stack)}")
        for f, shape in self._ref_shape.items():
            ids = refs[f]
            if ids.dtype.kind not in "iu" or ids.ndim < 1 or ids.shape[1:] != shape:
                raise SpecMismatch(f"frame ids {f}: {ids.dtype.name}{list(ids.shape)}, expected integer "
                                   f"{['B', *shape]}".replace("'", ""))
        if n_f > self._fcap:
            raise SpecMismatch(f"a chunk of {n_f} frames does not fit a frame ring of {self._fcap}")
        return n_f

    def insert(self, stream: str, frame_base: int, frames: Mapping[str, np.ndarray],
               batch: Mapping[str, np.ndarray], refs: Mapping[str, np.ndarray],
               priorities: np.ndarray | None = None) -> InsertResult:
        """Store one chunk of actor ``stream``: frames with ids ``frame_base .. frame_base+F-1``
        and transitions whose frame fields are ids (into this chunk or the stream's earlier
        ones). Transitions with an id that resolves to no stored frame are dropped and counted.

        Raises:
            SpecMismatch: frames, ids or columns do not match the store (nothing is stored).
            ValueError: bad priorities (nothing is stored).
        """
        res = self.insert_many([FrameChunk(stream, frame_base, frames, batch, refs, priorities)])[0]
        if isinstance(res, Exception):
            raise res
        return res

    def insert_many(self, chunks: Sequence["FrameChunk"]) -> list[InsertResult | SpecMismatch | ValueError]:
        """Store several chunks, in order, with exactly the outcome of one :meth:`insert` per
        chunk (the same keys, drops and stored transitions; only the split of lost items between
        the ``evicted_by_frames`` counter and capacity eviction may differ), but one transition
        insert, one eviction and one reference update for all of them: the per-call cost is paid
        once per call.

        Returns, per chunk, its :class:`InsertResult`, or the ``SpecMismatch`` / ``ValueError``
        that refused it (a refused chunk stores nothing; the others are unaffected)."""
        out: list[Any] = [None] * len(chunks)
        todo: list[tuple[int, FrameChunk, int, int, np.ndarray | None]] = []
        for i, c in enumerate(chunks):
            try:
                todo.append((i, c, *self._precheck(c)))
            except (SpecMismatch, ValueError) as e:
                out[i] = e
        # groups whose frames fit the ring once (a chunk alone always does: check())
        group: list[tuple[int, FrameChunk, int, int, np.ndarray | None]] = []
        nf = 0
        for t in todo:
            if group and nf + t[2] > self._fcap:
                self._insert_group(group, out)
                group, nf = [], 0
            group.append(t)
            nf += t[2]
        if group:
            self._insert_group(group, out)
        return out

    def _precheck(self, c: "FrameChunk") -> tuple[int, int, np.ndarray | None]:
        """Everything about one chunk that can refuse it; returns ``(frame count, items,
        float64 priorities or None)``."""
        n_f = self.check(c.frames, c.refs)
        fb = c.frame_base
        if isinstance(fb, bool) or not isinstance(fb, (int, np.integer)) or fb < 0:
            raise ValueError(f"frame_base must be an int >= 0, got {fb!r}")
        n = self._batch_size(c.batch, c.refs)
        p = None if c.priorities is None else _check_priorities(c.priorities, n, "priorities")
        return n_f, n, p

    def _batch_size(self, batch: Mapping[str, np.ndarray], refs: Mapping[str, np.ndarray]) -> int:
        """The chunk's batch size B after the columns' check: ``batch`` as the spec's columns and
        ``refs`` (already checked by :meth:`check`) as the gkey columns they become. A chunk that
        fails the fast comparison is checked again by the full one, which raises the error."""
        if isinstance(batch, Mapping) and batch.keys() == self._col_keys:
            n = -1
            for name, dtype, shape in self._col_checks:
                v = batch[name]
                if type(v) is not np.ndarray or v.dtype != dtype:
                    break
                vs = v.shape
                if vs[1:] != shape or len(vs) != len(shape) + 1 or (n >= 0 and vs[0] != n):
                    break
                n = vs[0]
            else:
                if n >= 0 and all(ids.shape[0] == n for ids in refs.values()):
                    return n
        return self._full_batch_size(batch, refs)

    def _full_batch_size(self, batch: Mapping[str, np.ndarray], refs: Mapping[str, np.ndarray]) -> int:
        return self._inner._validate_batch({**batch, **{GKEY_PREFIX + f: self._gkey_shape(f, refs[f]) for f in refs}})

    def _insert_group(self, group: list[tuple[int, "FrameChunk", int, int, np.ndarray | None]], out: list[Any]) -> None:
        """Chunks that passed :meth:`_precheck`, whose frames together fit the ring once."""
        # Older transitions that reference a frame any of these chunks overwrite go first
        # (one chunk at a time would evict them chunk by chunk: the same items).
        self._evict_for(sum(t[2] for t in group))
        mp = self._inner.max_priority
        cols: list[dict[str, np.ndarray]] = []
        prios: list[np.ndarray] = []
        given = False
        counts: list[tuple[int, int, int]] = []  # (chunk index, stored, dropped)
        for i, c, n_f, n, p in group:
            fb = int(c.frame_base)
            hist = self._streams.get(c.stream)
            if hist is None or fb < hist.end:  # new actor, or one that restarted
                hist = self._streams[c.stream] = _History(deque(), deque(), deque())
            if n_f:
                self._copy_frames(c.frames, n_f)
                hist.bases.append(fb)
                hist.counts.append(n_f)
                hist.gbases.append(self._frames_total - n_f)
                hist.end = fb + n_f
                floor = self._frames_total - self._fcap
                while hist.bases and (hist.gbases[0] + hist.counts[0] <= floor or len(hist.bases) > MAX_HISTORY):
                    hist.bases.popleft()
                    hist.counts.popleft()
                    hist.gbases.popleft()
            # ids of one item flattened: [n, prod(id shape)]
            gk = {}
            complete = True  # every id resolved (the common case: no -1 to look for)
            for f, ids in c.refs.items():
                g, whole = self._resolve(hist, np.asarray(ids, np.int64), None if c.bounds is None else c.bounds.get(f))
                gk[f] = g.reshape(n, self._ref_width[f])
                complete &= whole
            ok = None
            if not complete:
                for g in gk.values():
                    good = (g >= 0).all(axis=1)
                    ok = good if ok is None else ok & good
            dropped = int(n - np.count_nonzero(ok)) if n and ok is not None else 0
            data = dict(c.batch)
            for f, g in gk.items():
                data[GKEY_PREFIX + f] = g
            if p is None:
                p = np.full(n, mp, np.float64)  # what insert() alone would give: the running max
            else:
                given = True
                if n:
                    mp = max(mp, float(p.max()))
            if dropped:
                self.unresolved += dropped
                data = {k: v[ok] for k, v in data.items()}
                p = p[ok]
            cols.append(data)
            prios.append(p)
            counts.append((i, n - dropped, dropped))
        if len(cols) == 1:
            data, p = cols[0], prios[0]
        else:
            data = {k: np.concatenate([d[k] for d in cols]) for k in cols[0]}
            p = np.concatenate(prios)
        keys = self._inner.insert(data, p if given else None)
        off = 0
        for i, m, dropped in counts:
            out[i] = InsertResult(keys[off:off + m], dropped)
            off += m
        if not keys.size:
            return
        # A transition whose frame a later chunk of this group overwrote: what that chunk's
        # insert() would have done, evict it with everything older.
        floor = self._frames_total - self._fcap
        live = keys >= keys[-1] - (self._inner.capacity - 1)
        gcols = [data[GKEY_PREFIX + f] for f in self._ref_stack]
        if floor > 0:
            lost = np.zeros(keys.size, bool)
            for g in gcols:
                lost |= (g < floor).any(axis=1)
            if lost.any():
                self.evicted_by_frames += self._inner.evict_before(int(keys[lost].max()) + 1)
                live &= keys > keys[lost].max()
        if live.any():
            kept = keys[live]
            for g in gcols:
                gl = g[live]
                np.maximum.at(self._last_ref, (gl % self._fcap).ravel(), np.repeat(kept, gl.shape[1]))

    def _gkey_shape(self, f: str, ids: np.ndarray) -> np.ndarray:
        """A zero-size stand-in with the shape the column will have (for batch validation)."""
        k = max(math.prod(self._ref_shape[f]), 1)
        return np.broadcast_to(np.zeros((), np.int64), (ids.shape[0], k))

    def _evict_for(self, n_f: int) -> None:
        """Before ``n_f`` new frames go in: evict the transitions that reference a frame in the
        slots they overwrite (and, FIFO, every older one)."""
        cap = self._fcap
        start = self._frames_total
        new_floor = start + n_f - cap
        if new_floor > 0:  # frames [max(0, old floor), new_floor) are overwritten
            lo = max(0, start - cap)
            slots = np.arange(lo, new_floor) % cap
            newest = int(self._last_ref[slots].max()) if slots.size else -1
            if newest >= 0:
                self.evicted_by_frames += self._inner.evict_before(newest + 1)
            self._last_ref[slots] = -1

    def _copy_frames(self, frames: Mapping[str, np.ndarray], n_f: int) -> None:
        cap = self._fcap
        s0 = self._frames_total % cap
        n1 = min(n_f, cap - s0)
        for t, ring in self._frames.items():
            src = frames[t]
            ring[s0:s0 + n1] = src[:n1]
            if n_f > n1:
                ring[:n_f - n1] = src[n1:]
        self._frames_total += n_f

    def _resolve(self, hist: _History, ids: np.ndarray, bounds: tuple[int, int] | None = None) -> tuple[np.ndarray, bool]:
        """Stream frame ids -> global frame keys (``-1`` where no stored frame has that id), and
        whether every id resolved. ``bounds``: ``(ids.min(), ids.max())`` if known."""
        if not hist.bases:
            return np.full(ids.shape, -1, np.int64), not ids.size
        floor = self._frames_total - self._fcap
        base, cnt, gb = hist.bases[-1], hist.counts[-1], hist.gbases[-1]
        if not ids.size:
            return ids.copy(), True
        lo, hi = bounds if bounds is not None else (int(ids.min()), int(ids.max()))
        if lo >= base and hi < base + cnt:  # all in the newest chunk
            g = ids + (gb - base)
            if lo + (gb - base) >= floor:  # and that chunk's frames are all still in the ring
                return g, True
        else:
            bases = np.fromiter(hist.bases, np.int64, len(hist.bases))
            ends = bases + np.fromiter(hist.counts, np.int64, len(hist.counts))
            gbs = np.fromiter(hist.gbases, np.int64, len(hist.gbases))
            j = np.searchsorted(bases, ids, side="right") - 1
            jc = np.maximum(j, 0)
            g = gbs[jc] + ids - bases[jc]
            g[(j < 0) | (ids >= ends[jc])] = -1
        g[g < floor] = -1
        return g, False

    # ------------------------------------------------------------------ priorities
    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> int:
        return self._inner.update_priorities(keys, priorities)

    def raw_priorities(self) -> tuple[np.ndarray, np.ndarray]:
        return self._inner.raw_priorities()

    def remove(self, keys: np.ndarray) -> np.ndarray:
        """:meth:`InMemoryReplay.remove` (the frames stay until their ring overwrites them)."""
        return self._inner.remove(keys)

    @property
    def removed_total(self) -> int:
        return self._inner.removed_total

    def priorities_of(self, keys: np.ndarray) -> np.ndarray:
        return self._inner.priorities_of(keys)

    def start_at(self, first_key: int) -> None:
        self._inner.start_at(first_key)

    # ------------------------------------------------------------------ sampling
    def sample(self, batch_size: int, beta: float, rng: np.random.Generator | None = None,
               rows: bool = False) -> SampleBatch:
        """As :meth:`InMemoryReplay.sample`; frame fields come back as images/stacks, or with
        ``rows`` as :class:`~zenrl.common.protocol.Rows` of the frame rings, gathered when the
        reply is encoded (the caller holds off inserts until then)."""
        s = self._inner.sample(batch_size, beta, rng)
        data: dict[str, Any] = {}
        for k, v in s.data.items():
            if not k.startswith(GKEY_PREFIX):
                data[k] = v
        b = len(s)
        cap = self._fcap
        for f, shape in self._ref_shape.items():
            ring = self._frames[frame_table(f)]
            slots = s.data[GKEY_PREFIX + f].reshape(-1) % cap
            if rows:
                data[f] = Rows(ring, slots, (b, *shape, *ring.shape[1:]))
            else:
                data[f] = ring.take(slots, axis=0, mode="clip").reshape((b, *shape, *ring.shape[1:]))
        return SampleBatch(keys=s.keys, probabilities=s.probabilities, weights=s.weights, data=data)
