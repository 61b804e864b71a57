"""The replay's storage behind one interface, whatever it holds.

A replay stores either full observations (:class:`PlainStore`, an
:class:`~zenrl.replay.buffer.InMemoryReplay`) or, for image envs, transitions whose observations
are frame ids into frame rings (:class:`FrameStore`, a :class:`~zenrl.replay.frames.FrameReplay`).
Which one is chosen once, by :func:`allocate`, from the first chunk that is stored (or the first
record of the log). Ingest, the journal and sampling then use only the :class:`Store` interface:

* ``buffer``: the storage itself, for what both kinds share (``size``, ``capacity``,
  ``inserts_total``, ``sample``, ``update_priorities``, ``raw_priorities``, ``start_at``, ...);
* ``fits(chunk)``: ``""`` when a chunk's layout is the storage's, else why not (a ``spec``
  rejection);
* ``check(checker, chunks)``: the semantic checks (:mod:`zenrl.replay.checks`) of several chunks,
  one :class:`~zenrl.replay.checks.Rejection` or None per chunk;
* ``insert(chunks)``: store several chunks in order; per chunk a :class:`Stored` (its keys) or the
  ``SpecMismatch``/``ValueError`` that refused it alone;
* ``stats()``: the storage's own stats values.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, Sequence

import numpy as np

from zenrl.common import protocol as P
from zenrl.common.errors import MemoryTooSmall, SpecMismatch
from zenrl.common.specs import spec_nbytes, spec_of_batch
from zenrl.replay.buffer import InMemoryReplay
from zenrl.replay.checks import Checker, Rejection
from zenrl.replay.frames import FrameChunk, FrameReplay

log = logging.getLogger(__name__)

#: Column the service adds to every item: the weight version the actor acted with (policy lag).
POLICY_VERSION_FIELD = "meta/policy_version"


@dataclass(frozen=True)
class Chunk:
    """One decoded ``transitions`` message on its way to the store. ``data``: the message's flat
    fields ``{name: array[B, ...]}`` plus ``meta/policy_version`` int64[B]; ``source``: the key it
    arrived on (its last segment names the sender) or ``""``."""

    payload: bytes
    msg: P.TransitionBatch
    source: str
    data: dict[str, np.ndarray]

    @classmethod
    def of(cls, payload: bytes, msg: P.TransitionBatch, source: str = "") -> "Chunk":
        data = dict(msg.data)
        data[POLICY_VERSION_FIELD] = np.full(msg.batch_size, msg.policy_version, np.int64)
        return cls(payload, msg, source, data)

    @property
    def sender(self) -> str:
        return self.source or self.msg.actor_id

    @property
    def nbytes(self) -> int:
        """Bytes of the decoded arrays (views on the payload for those that travel raw)."""
        m = self.msg
        return sum(a.nbytes for a in self.data.values()) + sum(a.nbytes for a in (m.frames or {}).values())

    @property
    def stream(self) -> str:
        """Whose frame ids a frame-mode chunk's are: the actor named by the key it arrived on
        (the last segment), never the ``actor_id`` inside the payload, which anyone can write;
        the payload's name only for a journal record (written from a key-bound chunk)."""
        return self.source.rsplit("/", 1)[-1] if self.source else self.msg.actor_id


@dataclass(frozen=True)
class Stored:
    """What one chunk became in the store: ``keys`` int64[B'] of its stored transitions and
    ``dropped`` transitions it lost (frame ids that did not resolve; always 0 for plain storage)."""

    keys: np.ndarray
    dropped: int = 0


class Store(Protocol):
    """See the module docstring."""

    buffer: Any

    def fits(self, c: Chunk) -> str: ...

    def check(self, checker: Checker, chunks: Sequence[Chunk]) -> list[Rejection | None]: ...

    def insert(self, chunks: Sequence[Chunk]) -> list[Stored | SpecMismatch | ValueError]: ...

    def stats(self) -> dict[str, Any]: ...


def check_one(checker: Checker, c: Chunk) -> Rejection | None:
    """The semantic checks of one chunk alone, for either kind of storage."""
    if c.msg.frames is None:
        return checker.check(c.msg.data, c.msg.priorities)
    return (checker.check_frame_fields(c.msg.data, c.msg.frames) or checker.check_scalars(c.msg.data, c.msg.priorities)
            or checker.check_frames(c.msg.frames))


#: bytes a slot costs besides its fields: its key (int64), removed flag, and sum-tree nodes
SLOT_OVERHEAD_BYTES = 8 + 1 + 16


def machine_memory() -> tuple[int, str] | None:
    """The memory this process may use at most, and what sets it: the container's limit (cgroup
    v2 ``memory.max``, v1 ``memory.limit_in_bytes``) where one is below the machine's memory
    (``MemTotal``). None where neither can be read (not Linux)."""
    found: list[tuple[int, str]] = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                found.append((int(line.split()[1]) * 1024, "the machine's memory"))
    except (OSError, ValueError, IndexError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 1 << 60:  # "max" / a huge number: no limit
            found.append((int(text), f"the container's memory limit ({path})"))
    return min(found) if found else None


def memory_limit(share: int = 1) -> tuple[int, str] | None:
    """What one replay may take: :func:`machine_memory`, or 1/``share`` of it where ``share``
    replay services share the machine (``replay.replays_per_machine``)."""
    limit = machine_memory()
    if limit is None or share <= 1:
        return limit
    have, what = limit
    return have // share, f"1/{share} of {what} (replay.replays_per_machine = {share})"


def check_memory(items: int, bytes_per_item: int, limit: tuple[int, str] | None = None, warn: bool = True,
                 share: int = 1) -> None:
    """Raise :class:`MemoryTooSmall` when a ring of ``items`` slots of ``bytes_per_item`` field
    bytes (allocated lazily: its pages are committed as it fills) could not fit in ``limit``
    (default :func:`memory_limit` of ``share``) once full: the replay would be killed for memory
    hours into a run, restarted and killed again. With ``warn``, logs a warning when it would take
    more than 80% of it."""
    limit = memory_limit(share) if limit is None else limit
    if limit is None:
        return
    need = items * (bytes_per_item + SLOT_OVERHEAD_BYTES)
    have, what = limit
    gib = 1 << 30
    sized = (f"replay.capacity = {items:,} items of {bytes_per_item:,} bytes need {need / gib:.1f} GiB once full, "
             f"and {what} is {have / gib:.1f} GiB")
    if need > have:
        raise MemoryTooSmall(f"{sized}: lower replay.capacity, or set replay.max_bytes to the memory the replay may take")
    if warn and need > 0.8 * have:
        log.warning("%s: the replay alone would take %.0f%% of it once full (replay.max_bytes caps it)", sized,
                    100 * need / have)


def allocate(c: Chunk, rcfg: Any, seed: int, vetted: bool, first_key: int | None = None) -> Store:
    """The storage for a replay whose first stored chunk is ``c`` (frame mode when it carries
    frames), sized by the replay config ``rcfg``; its keys start at ``first_key`` (a restored log)
    or 0. ``vetted``: ``c``'s fields are known to be the env's (it passed the checks). Raises
    ``ValueError``/``SpecMismatch`` when no storage can be built from ``c``, :class:`MemoryTooSmall`
    when it could not fit in memory once full (:func:`check_memory`)."""
    # before anything is allocated (the slots' keys are written at once): the item's own fields
    # (all of it for full observations, a lower bound in frame mode), then the storage's own figure
    refs = c.msg.frame_refs() if c.msg.frames is not None else {}
    cols = spec_nbytes(spec_of_batch({k: v for k, v in c.data.items() if k not in refs}))
    share = rcfg.replays_per_machine
    check_memory(rcfg.capacity if rcfg.max_bytes is None else min(rcfg.capacity, rcfg.max_bytes // max(cols, 1)), cols,
                 warn=False, share=share)
    try:
        store: Store = (FrameStore.allocate(c, rcfg, seed) if c.msg.frames is not None
                        else PlainStore.allocate(c, rcfg, seed, vetted))
    except MemoryError as e:
        raise MemoryTooSmall(f"replay.capacity = {rcfg.capacity:,}: the replay's storage cannot be allocated ({e}); "
                             "lower replay.capacity, or set replay.max_bytes to the memory the replay may take") from None
    check_memory(store.buffer.capacity, store.buffer.bytes_per_item, share=share)
    if first_key is not None:
        store.buffer.start_at(first_key)
    return store


class PlainStore:
    """Full observations in an :class:`InMemoryReplay`. Several chunks are checked and inserted
    as one batch (one tree update), so their per-call costs are paid once per batch."""

    def __init__(self, buffer: InMemoryReplay, vetted: bool) -> None:
        self.buffer = buffer
        #: the storage's fields are known to be the env's: a batch that matches them needs only
        #: its values checked
        self.vetted = vetted
        self._sig = {k: (v.shape, np.dtype(v.dtype)) for k, v in buffer.spec.items()}
        #: the batch :meth:`check` combined, kept for the :meth:`insert` of the same chunks that
        #: follows it (concatenating a batch of chunks twice costs as much as the checks)
        self._combined: tuple[tuple[int, ...], dict[str, np.ndarray], np.ndarray | None] | None = None

    @classmethod
    def allocate(cls, c: Chunk, rcfg: Any, seed: int, vetted: bool) -> "PlainStore":
        spec = spec_of_batch(c.data)
        buf = InMemoryReplay(spec, capacity=rcfg.capacity, max_bytes=rcfg.max_bytes, alpha=rcfg.alpha,
                             uniform=rcfg.uniform, seed=seed)
        log.info("replay storage allocated: %d items x %d bytes, fields %s", buf.capacity,
                 buf.bytes_per_item, {k: (v.shape, v.dtype) for k, v in spec.items()})
        return cls(buf, vetted)

    def fits(self, c: Chunk) -> str:
        if c.msg.frames is not None:
            return "a frame-mode chunk, but this replay stores full observations"
        sig = self._sig
        if c.data.keys() != sig.keys():
            return f"fields {sorted(c.data)} differ from the replay's {sorted(sig)}"
        for k, a in c.data.items():
            shape, dt = sig[k]
            if a.shape[1:] != shape or a.dtype != dt:
                return f"field {k}: {a.dtype.name}{list(a.shape[1:])} differs from the replay's {dt.name}{list(shape)}"
        return ""

    def check(self, checker: Checker, chunks: Sequence[Chunk]) -> list[Rejection | None]:
        """One check of the combined batch; only when it fails are the chunks checked one by one
        to find the bad ones."""
        data, prios = self._combine(chunks)
        self._combined = (tuple(map(id, chunks)), data, prios)
        if not self.vetted:
            data = {k: v for k, v in data.items() if k != POLICY_VERSION_FIELD}
        if checker.check(data, prios, fields_checked=self.vetted) is None:
            return [None] * len(chunks)
        return [check_one(checker, c) for c in chunks]

    def insert(self, chunks: Sequence[Chunk]) -> list[Stored | SpecMismatch | ValueError]:
        cached, self._combined = self._combined, None
        if cached is not None and cached[0] == tuple(map(id, chunks)):
            data, prios = cached[1], cached[2]
        else:
            data, prios = self._combine(chunks)
        try:
            keys = self.buffer.insert(data, prios)
        except (SpecMismatch, ValueError) as e:
            if len(chunks) == 1:
                return [e]
            return [r for c in chunks for r in self.insert([c])]  # a refused chunk costs only itself
        out: list[Stored | SpecMismatch | ValueError] = []
        off = 0
        for c in chunks:
            out.append(Stored(keys[off:off + c.msg.batch_size]))
            off += c.msg.batch_size
        return out

    def stats(self) -> dict[str, Any]:
        return {}

    def _combine(self, chunks: Sequence[Chunk]) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """One batch ``{field: array[sum B, ...]}`` and its priorities from several chunks."""
        if len(chunks) == 1:
            return chunks[0].data, chunks[0].msg.priorities
        data = {k: np.concatenate([c.data[k] for c in chunks]) for k in chunks[0].data}
        if all(c.msg.priorities is not None for c in chunks):
            return data, np.concatenate([c.msg.priorities for c in chunks])
        # chunks without priorities take the running max, as on their own
        mp = np.float32(self.buffer.max_priority)
        return data, np.concatenate([c.msg.priorities if c.msg.priorities is not None
                                     else np.full(c.msg.batch_size, mp, np.float32) for c in chunks])


class FrameStore:
    """Transitions with frame ids in a :class:`FrameReplay` (each frame stored once). Chunks are
    checked one by one and inserted with one ``insert_many``."""

    def __init__(self, buffer: FrameReplay) -> None:
        self.buffer = buffer

    @classmethod
    def allocate(cls, c: Chunk, rcfg: Any, seed: int) -> "FrameStore":
        refs = c.msg.frame_refs()
        batch = {k: v for k, v in c.data.items() if k not in refs}
        # the ids' shape per item: [B] one frame, [B, k] a stack of k (Ape-X; an R2D2 sequence of
        # m+1 single frames has the same layout), [B, m+1, k] an R2D2 sequence of stacks
        ref_stack = {k: (0 if v.ndim == 1 else int(v.shape[1]) if v.ndim == 2 else tuple(int(d) for d in v.shape[1:]))
                     for k, v in refs.items()}
        buf = FrameReplay(spec_of_batch(batch), spec_of_batch(c.msg.frames), ref_stack, rcfg.capacity,
                          frames_per_item=rcfg.frames_per_item, max_bytes=rcfg.max_bytes, alpha=rcfg.alpha,
                          uniform=rcfg.uniform, seed=seed)
        log.info("replay storage allocated (frame mode): %d items, %d frames, %d bytes per item",
                 buf.capacity, buf.frame_capacity, buf.bytes_per_item)
        return cls(buf)

    def fits(self, c: Chunk) -> str:
        # the frame layout itself is checked by FrameReplay when the chunk is inserted
        return "" if c.msg.frames is not None else "a chunk of full observations, but this replay stores frames (frame mode)"

    def check(self, checker: Checker, chunks: Sequence[Chunk]) -> list[Rejection | None]:
        return [check_one(checker, c) for c in chunks]

    def insert(self, chunks: Sequence[Chunk]) -> list[Stored | SpecMismatch | ValueError]:
        fcs = []
        for c in chunks:
            refs = c.msg.frame_refs()
            batch = {k: v for k, v in c.data.items() if k not in refs}
            fcs.append(FrameChunk(c.stream, c.msg.frame_base, c.msg.frames, batch, refs, c.msg.priorities,
                                  c.msg.frame_id_bounds()))
        return [r if isinstance(r, Exception) else Stored(r.keys, r.dropped) for r in self.buffer.insert_many(fcs)]

    def stats(self) -> dict[str, Any]:
        b = self.buffer
        return {"frames_stored": b.frames_stored, "frames_unresolved_items": b.unresolved,
                "evicted_by_frames": b.evicted_by_frames}
