"""The zenrl wire protocol: key expressions and messages, in one module.

Every message is one msgpack map (an *envelope*)::

    {"v": PROTOCOL_VERSION, "t": "<message type>", <field>: <value>, ...}

Arrays travel as a map ``{"dtype": "<numpy dtype name>", "shape": [d0, d1, ...], "data": <bin>}``
where ``data`` is the C-order raw buffer (little-endian, as numpy stores it on every platform
zenrl runs on). A batch of arrays (transitions, parameters) is a map ``{name: array}`` with flat
names (``obs/lidar``; see :mod:`zenrl.common.specs`).

Decoding validates everything a peer could get wrong, and raises :class:`ProtocolError` naming
the field: the payload size cap, msgpack itself, the version, the message type, the exact set of
field names, value types, every integer field against its declared range (a signed int64 at
most: :data:`INT_RANGES`), array dtypes (a whitelist), shapes (at most MAX_NDIM dimensions of at
most MAX_DIM, at most MAX_ELEMENTS elements counting a zero dimension as one, so a zero cannot
hide huge dimensions) against the byte length, the bytes the compressed arrays of one message
declare (together at most :attr:`DecodeLimits.max_decoded_bytes`, each against the receiver's
spec where it has one), all before anything is allocated or decompressed; then consistent batch
sizes and finite floats where they matter (rewards, priorities, weights, gradients). No other
exception type escapes decoding for any input. Nothing is ever unpickled. docs/protocol.md
documents the same thing for third parties.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any, ClassVar, Iterable, Mapping, Union

import lz4.block
import msgpack
import msgspec
import numpy as np

from zenrl.common.errors import ConfigError, ProtocolError
from zenrl.common.specs import ALLOWED_DTYPES

PROTOCOL_VERSION = 1

#: Default cap on the size of one encoded message (bytes). Zenoh silently drops messages above
#: the receiver's ``max_message_size``; zenrl refuses them on both ends with a clear error.
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
#: Cap on the number of arrays in one batch map and on the number of dimensions of an array.
MAX_FIELDS = 256
MAX_NDIM = 8
#: Most items one SampleRequest may ask for.
MAX_SAMPLE_BATCH = 65536
#: Most replay shards a run may have (``replay.shards``).
MAX_REPLAY_SHARDS = 64
#: Range of every integer field (schema kinds "int" and "uint"): a signed int64 (int63 for
#: "uint"), so that any integer the protocol admits fits the numpy columns it may end up in.
INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1
INT_RANGES = {"int": (INT64_MIN, INT64_MAX), "uint": (0, INT64_MAX)}
#: Largest dimension of an array, and most elements one array may declare; a zero dimension
#: counts as one, so ``[2**32, 2**32, 0]`` is refused rather than overflowing a product later.
MAX_DIM = 1 << 30
MAX_ELEMENTS = 1 << 30
#: Largest frame id (``frame_base + F`` and every id stay below it, leaving int64 headroom for
#: the arithmetic on ids).
MAX_FRAME_ID = 1 << 62

_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
_FIELD_RE = re.compile(r"^[A-Za-z0-9_.\-/]{1,128}$")


# --------------------------------------------------------------------------------------------
# Key expressions. No key string is built anywhere else in zenrl.
# --------------------------------------------------------------------------------------------
def check_name(what: str, name: str) -> str:
    """Validate a run id, actor id or role used inside a key expression."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ProtocolError(what, f"{name!r} must be 1-64 characters of [A-Za-z0-9_.-]", "name")
    return name


def replay_shard(shard: int | None, shards: int) -> int | None:
    """The ``replay_shard`` of :class:`Keys` for a replay service of shard ``shard`` (None or an
    int) in a run of ``shards`` (``replay.shards``): None for an unsharded run (``shard`` None or
    0), else ``shard``, which must then be given and be in 0..shards-1 (ConfigError naming it)."""
    if shards == 1 and shard in (None, 0):
        return None
    if shard is None:
        raise ConfigError(f"replay.shards={shards}: give this replay its shard, 0..{shards - 1} "
                          "(zenrl replay --shard K, or ZENRL_REPLAY_SHARD)")
    if type(shard) is not int or not 0 <= shard < shards:
        raise ConfigError(f"replay shard {shard!r} is not in 0..{shards - 1} (replay.shards={shards})")
    return shard


def actor_shard(slot: int, shards: int) -> int | None:
    """The replay shard an actor of exploration slot ``slot`` writes to: ``slot % shards`` (None
    for an unsharded run). Elastic actors claim the lowest free slots, so they spread over the
    shards evenly as they join; an actor keeps its shard for its life."""
    return None if shards == 1 else int(slot) % shards


class Keys:
    """Key expressions of one run: everything lives under ``zenrl/<run>/``.

    ===============================  ===========  =========================================
    key                              kind         message
    ===============================  ===========  =========================================
    ``transitions/<actor>``          put          :class:`TransitionBatch`  actor -> replay
    ``replay/sample``                queryable    :class:`SampleRequest` -> :class:`SampleReply`
    ``replay/priorities``            put          :class:`PriorityUpdate`   learner -> replay
    ``weights``                      put          :class:`Weights`          learner -> actors
    ``learner/weights``              queryable    (empty) -> :class:`Weights` (latest)
    ``gradients/<worker>``           put          :class:`Gradients`        A3C worker -> learner
    ``unrolls/<actor>``              put          :class:`Unroll`           IMPALA actor -> learner
    ``episodes/<actor>``             put          :class:`EpisodeStats`     actor -> anyone
    ``eval``                         put          :class:`EvalResult`       evaluator -> anyone
    ``stats/<role>/<id>``            put          :class:`Stats`            every process
    ``alive/<role>/<id>``            liveliness   (token)                   every process
    ``slots/<k>/<actor>``            liveliness   (token)                   actor owning slot k
    ``quarantine/<actor>``           liveliness   (token)                   replay, while it drops <actor>
    ===============================  ===========  =========================================

    Sharded replay (``replay.shards`` = N > 1): ``Keys(run, replay_shard=k)`` names shard k's
    keys ``transitions/<k>/<actor>``, ``replay/<k>/sample`` and ``replay/<k>/priorities`` (k in
    0..N-1; one segment more than the unsharded keys, so no shard's subscription matches
    another's). ``replay_shard=None`` (N = 1) keeps the keys above; every other key is the same.
    """

    def __init__(self, run_id: str, replay_shard: int | None = None) -> None:
        self.run_id = check_name("run_id", run_id)
        self.prefix = f"zenrl/{run_id}"
        if replay_shard is not None and (type(replay_shard) is not int or not 0 <= replay_shard < MAX_REPLAY_SHARDS):
            raise ProtocolError("replay_shard", f"{replay_shard!r} must be an integer in 0..{MAX_REPLAY_SHARDS - 1}", "field")
        #: the replay shard these keys address (None: the unsharded replay)
        self.replay_shard = replay_shard
        self._shard = "" if replay_shard is None else f"/{replay_shard}"

    def transitions(self, actor_id: str) -> str:
        return f"{self.prefix}/transitions{self._shard}/{check_name('actor_id', actor_id)}"

    @property
    def transitions_all(self) -> str:
        return f"{self.prefix}/transitions{self._shard}/*"

    @property
    def sample(self) -> str:
        return f"{self.prefix}/replay{self._shard}/sample"

    @property
    def priorities(self) -> str:
        return f"{self.prefix}/replay{self._shard}/priorities"

    @property
    def weights(self) -> str:
        return f"{self.prefix}/weights"

    @property
    def weights_query(self) -> str:
        return f"{self.prefix}/learner/weights"

    def gradients(self, worker_id: str) -> str:
        return f"{self.prefix}/gradients/{check_name('worker_id', worker_id)}"

    @property
    def gradients_all(self) -> str:
        return f"{self.prefix}/gradients/*"

    def unrolls(self, actor_id: str) -> str:
        return f"{self.prefix}/unrolls/{check_name('actor_id', actor_id)}"

    @property
    def unrolls_all(self) -> str:
        return f"{self.prefix}/unrolls/*"

    def episodes(self, actor_id: str) -> str:
        return f"{self.prefix}/episodes/{check_name('actor_id', actor_id)}"

    @property
    def episodes_all(self) -> str:
        return f"{self.prefix}/episodes/*"

    @property
    def eval(self) -> str:
        return f"{self.prefix}/eval"

    def stats(self, role: str, proc_id: str) -> str:
        return f"{self.prefix}/stats/{check_name('role', role)}/{check_name('id', proc_id)}"

    @property
    def stats_all(self) -> str:
        return f"{self.prefix}/stats/**"

    def alive(self, role: str, proc_id: str) -> str:
        return f"{self.prefix}/alive/{check_name('role', role)}/{check_name('id', proc_id)}"

    def alive_role(self, role: str) -> str:
        """Liveliness tokens of every process of one role."""
        return f"{self.prefix}/alive/{check_name('role', role)}/*"

    @property
    def alive_all(self) -> str:
        return f"{self.prefix}/alive/**"

    def slot_token(self, slot: int, actor_id: str) -> str:
        """Liveliness token an actor holds while it owns exploration slot ``slot``."""
        if not isinstance(slot, int) or slot < 0:
            raise ProtocolError("slot", f"{slot!r} must be a non-negative integer", "field")
        return f"{self.prefix}/slots/{slot}/{check_name('actor_id', actor_id)}"

    def quarantined(self, actor_id: str) -> str:
        """Liveliness token the replay holds while it drops ``actor_id``'s chunks."""
        return f"{self.prefix}/quarantine/{check_name('actor_id', actor_id)}"

    @property
    def quarantined_all(self) -> str:
        return f"{self.prefix}/quarantine/*"

    def slot_holders(self, slot: int | None = None) -> str:
        return f"{self.prefix}/slots/{'*' if slot is None else int(slot)}/*"

    def parse_slot(self, key: str) -> tuple[int, str]:
        """``zenrl/<run>/slots/<k>/<actor>`` -> ``(k, actor)``."""
        parts = str(key).split("/")
        if len(parts) != 5 or parts[2] != "slots" or not parts[3].isdigit():
            raise ProtocolError("key", f"{key!r} is not a slot key of run {self.run_id}")
        return int(parts[3]), parts[4]

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``zenrl/<run>/alive/<role>/<id>`` -> ``(role, id)``."""
        parts = str(key).split("/")
        if len(parts) != 5 or parts[2] != "alive":
            raise ProtocolError("key", f"{key!r} is not a liveliness key of run {self.run_id}")
        return parts[3], parts[4]


# --------------------------------------------------------------------------------------------
# Arrays
# --------------------------------------------------------------------------------------------
_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
# little-endian (or byte-order-free) dtype -> wire name; a dict lookup, where ``dtype.name``
# costs ~1.6 us (twice per array, it was ~80% of encoding a 7-array chunk: 28 -> ~5 us)
_WIRE_NAMES = {dt.newbyteorder("<"): name for name, dt in _DTYPES.items()}


#: Array codecs a sender may declare in the array map (uint8 arrays only).
CODECS = ("lz4",)
#: uint8 arrays smaller than this travel raw even when compression is asked for.
MIN_COMPRESS_BYTES = 4096
#: The lz4 block format cannot expand data by more than ~255x: a declared size beyond this
#: factor of the compressed bytes is a lie (a decompression bomb) and is refused unread.
LZ4_MAX_RATIO = 255


class Rows:
    """An array not gathered yet: rows ``index`` (int64[N]) of ``source`` ([S, *row]), as an array
    of ``shape`` (N * prod(row) elements in all). :meth:`Message.encode` gathers it straight into
    the payload, one pass over its bytes where gathering and then packing takes two: a replay's
    sample reply of 128 stacks of 84x84 frames is 7 MB. The caller keeps ``source`` unchanged
    until the encode returns (the replay holds its lock)."""

    __slots__ = ("source", "index", "shape", "dtype")

    def __init__(self, source: np.ndarray, index: np.ndarray, shape: tuple[int, ...]) -> None:
        if math.prod(shape) != index.shape[0] * math.prod(source.shape[1:]):
            raise ValueError(f"rows {index.shape[0]} x {list(source.shape[1:])} do not make shape {list(shape)}")
        self.source, self.index, self.shape, self.dtype = source, index, tuple(shape), source.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize

    def write(self, out: np.ndarray) -> None:
        """Gather into ``out`` (C-contiguous, this dtype, ``nbytes`` bytes)."""
        self.source.take(self.index, axis=0, mode="clip", out=out.reshape(self.index.shape[0], *self.source.shape[1:]))

    def array(self) -> np.ndarray:
        return self.source.take(self.index, axis=0, mode="clip").reshape(self.shape)


def _map_header(n: int) -> bytes:
    """msgpack's header of a map of ``n`` entries, as ``msgpack.packb`` writes it."""
    if n <= 15:
        return bytes((0x80 | n,))
    if n <= 0xFFFF:
        return b"\xde" + n.to_bytes(2, "big")
    return b"\xdf" + n.to_bytes(4, "big")


def _bin_header(n: int) -> bytes:
    """msgpack's header of ``n`` bytes of bin, as ``msgpack.packb(use_bin_type=True)`` writes it."""
    if n <= 0xFF:
        return b"\xc4" + n.to_bytes(1, "big")
    if n <= 0xFFFF:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


def _has_rows(v: Any) -> bool:
    return type(v) is Rows or (type(v) is dict and any(_has_rows(x) for x in v.values()))


def _pack_with_rows(env: dict[str, Any]) -> bytearray:
    """``msgpack.packb(env, use_bin_type=True)`` of an envelope whose array maps may hold
    :class:`Rows` as their data, the same bytes as packing the gathered arrays: the maps around
    them are written here, every other value by msgpack, and the rows gathered into their place
    in the payload."""
    pieces: list[bytes | Rows] = []

    def emit(v: Any) -> None:
        if type(v) is Rows:
            pieces.append(_bin_header(v.nbytes))
            pieces.append(v)
        elif type(v) is dict and _has_rows(v):
            pieces.append(_map_header(len(v)))
            for k, x in v.items():
                pieces.append(msgpack.packb(k, use_bin_type=True))
                emit(x)
        else:
            pieces.append(msgpack.packb(v, use_bin_type=True))

    emit(env)
    out = bytearray(sum(p.nbytes if type(p) is Rows else len(p) for p in pieces))
    pos = 0
    for p in pieces:
        if type(p) is Rows:
            n = p.nbytes
            if n:
                p.write(np.frombuffer(out, dtype=p.dtype, count=n // p.dtype.itemsize, offset=pos))
        else:
            n = len(p)
            out[pos:pos + n] = p
        pos += n
    return out


def encode_array(a: "np.ndarray | Rows", codec: str | None = None) -> dict[str, Any]:
    """``np.ndarray`` -> wire map; one copy at most (only if ``a`` is not C-contiguous or is
    big-endian). ``codec`` ("lz4"): uint8 arrays of at least MIN_COMPRESS_BYTES are compressed
    (lz4 block format, the decompressed byte count declared as ``size``). :class:`Rows` of a
    wire dtype stay rows (the map's data), gathered when the message is packed."""
    if type(a) is Rows:
        name = _WIRE_NAMES.get(a.dtype)
        if codec is None and name is not None and a.nbytes:
            return {"dtype": name, "shape": list(a.shape), "data": a}
        a = a.array()
    a = np.ascontiguousarray(a)
    if codec is not None and a.dtype == np.uint8 and a.nbytes >= MIN_COMPRESS_BYTES:
        if codec not in CODECS:
            raise ProtocolError("codec", f"{codec!r} is not one of {list(CODECS)}", "field")
        return {"dtype": "uint8", "shape": list(a.shape), "codec": codec, "size": a.nbytes,
                "data": lz4.block.compress(memoryview(a).cast("B"), store_size=False)}
    name = _WIRE_NAMES.get(a.dtype)
    if name is None:
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
            name = _WIRE_NAMES.get(a.dtype)
        if name is None:
            raise ProtocolError("dtype", f"{a.dtype.name} is not a wire dtype", "dtype")
    data = memoryview(a).cast("B") if a.size else b""
    return {"dtype": name, "shape": list(a.shape), "data": data}


_ARRAY_KEYS = {"dtype", "shape", "data"}
_PACKED_KEYS = {"dtype", "shape", "data", "codec", "size"}
#: what an array map's ``data`` may be: bin as msgpack decodes it, or a view on the payload
#: (:func:`_unpack_views`)
_BIN = (bytes, bytearray, memoryview)
_SHAPE_RULE = f"must be a list of <= {MAX_NDIM} ints in 0..{MAX_DIM} of at most {MAX_ELEMENTS} elements (a 0 counted as 1)"


def declared_elements(name: str, shape: Any) -> int:
    """The element count of a declared ``shape`` (a list of ints), after checking it against
    MAX_NDIM, MAX_DIM and MAX_ELEMENTS (a zero dimension counted as one, so a zero never hides
    huge dimensions). Raises :class:`ProtocolError` (reason ``shape``) naming ``name``."""
    if type(shape) is not list or len(shape) > MAX_NDIM:
        raise ProtocolError(f"{name}.shape", f"{shape!r:.200} {_SHAPE_RULE}", "shape")
    n = bound = 1
    for d in shape:
        if type(d) is not int or not 0 <= d <= MAX_DIM:
            raise ProtocolError(f"{name}.shape", f"{shape!r:.200} {_SHAPE_RULE}", "shape")
        n *= d
        bound *= d or 1
    if bound > MAX_ELEMENTS:
        raise ProtocolError(f"{name}.shape", f"{shape!r:.200} {_SHAPE_RULE}", "shape")
    return n


#: Default cap on the bytes the compressed arrays of one message declare together (what
#: decompressing them would allocate); see :class:`DecodeLimits`.
DEFAULT_MAX_DECODED_BYTES = 256 * 1024 * 1024


@dataclass(frozen=True)
class DecodeLimits:
    """What a receiver admits beyond the protocol's own bounds, checked from the declared numbers
    of the envelope before any array is decompressed.

    ``max_decoded_bytes``: most bytes the compressed arrays of one message may declare together
    (raw arrays are read-only views on the payload, so the message cap already bounds them).
    ``packed``: None (the receiver has no spec), or the compressed arrays its spec allows:
    ``{path: item shapes}`` with paths such as ``"data.obs"`` or ``"frames.obs"`` and the shapes
    one row (``shape[1:]``) may have; a compressed array elsewhere, or of another item shape, is
    refused unread (reason ``spec``)."""

    max_decoded_bytes: int = DEFAULT_MAX_DECODED_BYTES
    packed: Mapping[str, tuple[tuple[int, ...], ...]] | None = None


_DEFAULT_LIMITS = DecodeLimits()


def decode_array(name: str, m: Any) -> np.ndarray:
    """Wire map -> read-only ``np.ndarray`` view on the payload (no copy unless compressed). An
    ``np.ndarray`` is one :func:`_wire_map` already decoded (no wire value decodes to one)."""
    if type(m) is np.ndarray:
        return m
    if type(m) is not dict or m.keys() != _ARRAY_KEYS:
        if type(m) is dict and m.keys() == _PACKED_KEYS:
            return _decode_packed(name, m)
        raise ProtocolError(name, "must be a map with exactly dtype, shape, data (and codec, size when compressed)", "array")
    dtype, shape, data = m["dtype"], m["shape"], m["data"]
    dt = _DTYPES.get(dtype) if type(dtype) is str else None
    if dt is None:
        raise ProtocolError(f"{name}.dtype", f"{dtype!r:.100} is not one of {sorted(ALLOWED_DTYPES)}", "dtype")
    if type(shape) is not list or len(shape) > MAX_NDIM:
        raise ProtocolError(f"{name}.shape", f"{shape!r:.200} {_SHAPE_RULE}", "shape")
    expected = dt.itemsize
    for d in shape:
        if type(d) is not int or d < 0:
            raise ProtocolError(f"{name}.shape", f"{shape!r:.200} {_SHAPE_RULE}", "shape")
        expected *= d
    if not expected:
        # a non-empty array's bytes bound its shape (the message cap is at most 1 GiB); an
        # empty one's dimensions must be bounded on their own (a zero hides the rest)
        declared_elements(name, shape)
    if type(data) is not bytes and not isinstance(data, _BIN):
        raise ProtocolError(f"{name}.data", "must be bin", "array")
    if expected != len(data):
        raise ProtocolError(f"{name}.data", f"holds {len(data)} bytes; dtype {dtype} and shape {shape} need {expected}", "shape")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _check_packed_header(name: str, m: dict[str, Any]) -> int:
    """A compressed array map's codec, dtype, shape and declared ``size`` (the decompressed
    bytes, which must be the shape's); returns that size. Reads no data."""
    codec, size, dtype, shape = m["codec"], m["size"], m["dtype"], m["shape"]
    if codec not in CODECS:
        raise ProtocolError(f"{name}.codec", f"{codec!r:.100} is not one of {list(CODECS)}", "codec")
    if dtype != "uint8":
        raise ProtocolError(f"{name}.dtype", f"compressed arrays must be uint8, got {dtype!r:.100}", "dtype")
    expected = declared_elements(name, shape)
    if type(size) is not int or size != expected:
        raise ProtocolError(f"{name}.size", f"declares {size!r:.100} decompressed bytes; uint8 shape {shape} needs {expected}", "shape")
    data = m["data"]
    if isinstance(data, _BIN) and size > LZ4_MAX_RATIO * len(data) + 64:
        raise ProtocolError(f"{name}.size", f"declares {size} bytes from {len(data)} compressed bytes, more than "
                            f"{codec} can expand; refused unread", "bomb")
    return size


def _decode_packed(name: str, m: dict[str, Any]) -> np.ndarray:
    """A compressed array: every declared number is checked before a byte is decompressed."""
    codec, size, dtype, shape, data = m["codec"], m["size"], m["dtype"], m["shape"], m["data"]
    _check_packed_header(name, m)
    if not isinstance(data, _BIN):
        raise ProtocolError(f"{name}.data", "must be bin", "array")
    try:
        raw = lz4.block.decompress(data, uncompressed_size=size)
    except lz4.block.LZ4BlockError:
        raise ProtocolError(f"{name}.data", f"is not valid {codec} data for {size} bytes", "codec") from None
    if len(raw) != size:
        raise ProtocolError(f"{name}.data", f"decompresses to {len(raw)} bytes, declared {size}", "codec")
    return np.frombuffer(raw, dtype=np.uint8).reshape(shape)


_good_field_names: set[str] = set()


def _check_field_name(name: str, k: Any) -> None:
    if k in _good_field_names:
        return
    if not isinstance(k, str) or not _FIELD_RE.match(k):
        raise ProtocolError(f"{name}", f"array name {k!r:.140} must be 1-128 characters of [A-Za-z0-9_.-/]", "name")
    if len(_good_field_names) < 4096:
        _good_field_names.add(k)


def encode_arrays(arrays: Mapping[str, "np.ndarray | Rows"], codec: str | None = None) -> dict[str, Any]:
    return {k: encode_array(v if type(v) is Rows else np.asarray(v), codec) for k, v in arrays.items()}


def decode_arrays(name: str, m: Any, *, require_finite: bool = False, batch: int | None = None) -> dict[str, np.ndarray]:
    """Decode a map of arrays. With ``batch`` every array's first dimension must equal it."""
    if not isinstance(m, dict) or not m:
        raise ProtocolError(name, "must be a non-empty map of arrays", "array")
    if len(m) > MAX_FIELDS:
        raise ProtocolError(name, f"has {len(m)} arrays, more than {MAX_FIELDS}", "size")
    out = {}
    for k, v in m.items():
        _check_field_name(name, k)
        a = decode_array(f"{name}.{k}", v)
        if batch is not None and (a.ndim == 0 or a.shape[0] != batch):
            raise ProtocolError(f"{name}.{k}", f"batch size {a.shape[:1]} differs from {batch}", "batch")
        if require_finite and a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ProtocolError(f"{name}.{k}", "contains NaN or Inf", "nonfinite")
        out[k] = a
    return out


# --------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------
_REGISTRY: dict[str, type["Message"]] = {}


@dataclass(frozen=True)
class Message:
    """Base of every wire message. Subclasses set ``TYPE`` and may override ``_validate``.

    ``encode()`` returns ``bytes``; ``Cls.decode(payload)`` validates and returns an instance.
    """

    TYPE: ClassVar[str] = ""
    #: field name -> how to check/convert it: "int", "uint", "float", "str", "name", "bool",
    #: "arrays", "arrays?" (optional), "array", "array?", "map" (str -> scalar), "floats"
    SCHEMA: ClassVar[dict[str, str]] = {}
    #: optional fields left out of the envelope when None (added to a message type later, so
    #: peers that do not use them see the same bytes as before)
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset()
    #: integer fields whose range is narrower than their kind's (:data:`INT_RANGES`)
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {}
    #: the view reader (:func:`_unpack_views`) hands plain arrays to the checks already made
    #: (:func:`_wire_map`); a type whose ``_precheck`` reads the envelope's array maps must
    #: leave this False, so that it sees maps
    DIRECT_ARRAYS: ClassVar[bool] = False

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if cls.TYPE:
            _REGISTRY[cls.TYPE] = cls

    # -- encode ---------------------------------------------------------------------------
    def encode(self, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, codec: str | None = None) -> bytes | bytearray:
        """``codec`` ("lz4" or None): compress the uint8 arrays of the array maps. A message
        holding :class:`Rows` comes back as a bytearray (the same bytes, gathered in place)."""
        env: dict[str, Any] = {"v": PROTOCOL_VERSION, "t": self.TYPE}
        rows = False
        for name, kind in _encode_plan(type(self)):
            v = getattr(self, name)
            if v is None and name in self.OMIT_NONE:
                continue
            if v is None or kind == 0:
                env[name] = v
            elif kind == 2:
                env[name] = encode_arrays(v, codec)
                rows = rows or any(type(x) is Rows for x in v.values())
            else:
                rows = rows or type(v) is Rows
                env[name] = encode_array(v if type(v) is Rows else np.asarray(v))
        out = _pack_with_rows(env) if rows else msgpack.packb(env, use_bin_type=True)
        if len(out) > max_bytes:
            raise ProtocolError("payload", f"{self.TYPE} message of {len(out)} bytes exceeds the cap of {max_bytes} bytes; send smaller chunks", "size")
        return out

    # -- decode ---------------------------------------------------------------------------
    @classmethod
    def decode(cls, payload: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
               limits: DecodeLimits | None = None) -> "Message":
        """Validate and decode; ``limits``: the receiver's :class:`DecodeLimits` (default: the
        protocol's decoded-bytes cap, no spec)."""
        env = _unpack_views(cls, payload, max_bytes)
        if env["t"] != cls.TYPE:
            raise ProtocolError("t", f"expected message type {cls.TYPE!r:.100}, got {env['t']!r:.100}", "type")
        return cls._from_envelope(env, limits or _DEFAULT_LIMITS)

    @classmethod
    def _from_envelope(cls, env: dict[str, Any], limits: DecodeLimits = _DEFAULT_LIMITS) -> "Message":
        names = _field_names(cls)
        got = env.keys() - {"v", "t"}
        missing = sorted(n for n in names - got if not cls.SCHEMA[n].endswith("?"))
        if missing:
            raise ProtocolError(missing[0], f"missing from {cls.TYPE} message", "field")
        unknown = sorted(map(str, got - names))
        if unknown:
            raise ProtocolError(unknown[0][:100], f"is not a field of {cls.TYPE} messages", "field")
        cls._precheck(env)
        _check_declared(cls, env, limits)
        rng = cls.RANGES
        kw = {n: _check(n, cls.SCHEMA[n], env.get(n), rng.get(n)) for n in names}
        msg = cls(**kw)
        msg._validate()
        return msg

    @staticmethod
    def _precheck(env: dict[str, Any]) -> None:
        """Checks of the envelope's declared numbers before any array is decoded; raise
        ProtocolError."""

    def _validate(self) -> None:
        """Cross-field checks of a decoded message; raise ProtocolError."""


_FIELD_NAMES: dict[type, frozenset[str]] = {}
_ENCODE_PLANS: dict[type, tuple[tuple[str, int], ...]] = {}


def _encode_plan(cls: type) -> tuple[tuple[str, int], ...]:
    """``(field, 0 plain | 1 array | 2 arrays)`` in field order, built once per message class
    (``dataclasses.fields`` and the schema lookups cost a few us per message)."""
    plan = _ENCODE_PLANS.get(cls)
    if plan is None:
        kinds = [(f.name, cls.SCHEMA[f.name]) for f in fields(cls)]
        plan = _ENCODE_PLANS[cls] = tuple((n, 2 if k.startswith("arrays") else 1 if k.startswith("array") else 0)
                                          for n, k in kinds)
    return plan


def _field_names(cls: type) -> frozenset[str]:
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = frozenset(f.name for f in fields(cls))
    return names


def _unpack(payload: Any, max_bytes: int) -> dict[str, Any]:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise ProtocolError("payload", f"must be bytes, got {type(payload).__name__}", "malformed")
    if len(payload) > max_bytes:
        raise ProtocolError("payload", f"{len(payload)} bytes exceeds the cap of {max_bytes} bytes", "size")
    try:
        env = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise ProtocolError("payload", f"is not valid msgpack ({type(e).__name__})", "malformed") from None
    if not isinstance(env, dict):
        raise ProtocolError("payload", f"must be a msgpack map, got {type(env).__name__}", "malformed")
    _check_envelope(env)
    return env


def _check_envelope(env: dict[str, Any]) -> None:
    if env.get("v") != PROTOCOL_VERSION:
        raise ProtocolError("v", f"protocol version {env.get('v')!r} is not supported (this is version {PROTOCOL_VERSION})", "version")
    if not isinstance(env.get("t"), str):
        raise ProtocolError("t", "message type is missing", "type")


class _WireArray(msgspec.Struct, forbid_unknown_fields=True):
    """An array map as :func:`_unpack_views` reads it: ``data`` a view on the payload. The
    types are those msgpack's reader gives a well-formed map; a map of any other form is left to
    that reader."""

    dtype: str
    shape: list[int]
    data: memoryview
    codec: Union[str, msgspec.UnsetType] = msgspec.UNSET
    size: Union[int, msgspec.UnsetType] = msgspec.UNSET


_VIEW_DECODERS: dict[type, Any] = {}


def _view_decoder(cls: type["Message"]) -> Any:
    """A msgspec decoder of ``cls``'s envelope that reads its array maps' data as views on the
    payload; every other value as msgpack decodes it (built once per class)."""
    dec = _VIEW_DECODERS.get(cls)
    if dec is None:
        many, one = dict[str, _WireArray] | None, _WireArray | None
        kinds = {n: many if k.startswith("arrays") else one if k.startswith("array") else Any for n, k in cls.SCHEMA.items()}
        spec = [(n, kinds.get(n, Any), msgspec.UNSET) for n in ("v", "t", *(f.name for f in fields(cls)))]
        env = msgspec.defstruct(f"_{cls.__name__}Envelope", spec, forbid_unknown_fields=True)
        dec = _VIEW_DECODERS[cls] = msgspec.msgpack.Decoder(env)
    return dec


#: uint8 data at least this long stays a view on the payload; other data is copied out as
#: msgpack would (a view at an odd offset would give numbers unaligned arrays, slower to compute
#: on; a short copy costs less than the view's bookkeeping)
VIEW_MIN_BYTES = 64 * 1024


def _wire_map(w: _WireArray, direct: bool = True) -> np.ndarray | dict[str, Any]:
    """A wire array as msgspec read it -> with ``direct`` (the message type's
    :attr:`Message.DIRECT_ARRAYS`), the array :func:`decode_array` would make of it when it is a
    plain one that function accepts (:func:`_plain_array`: what every honest chunk sends);
    otherwise the map msgpack would have given, which ``decode_array`` checks and, if it must,
    refuses with the reason. The short cut skips building the map and reading it back, a few
    microseconds per array."""
    if direct:
        a = _plain_array(w)
        if a is not None:
            return a
    data = w.data
    if w.dtype != "uint8" or len(data) < VIEW_MIN_BYTES:
        data = bytes(data)
    m = {"dtype": w.dtype, "shape": w.shape, "data": data}
    if w.codec is not msgspec.UNSET:
        m["codec"] = w.codec
    if w.size is not msgspec.UNSET:
        m["size"] = w.size
    return m


def _unpack_views(cls: type["Message"], payload: Any, max_bytes: int) -> dict[str, Any]:
    """:func:`_unpack` of a ``cls`` message whose large uint8 arrays (images, frames; at least
    :data:`VIEW_MIN_BYTES`) stay in the payload: the arrays decoded from them are read-only
    views on ``payload``, not copies (a 64x64 camera chunk's frames are most of its bytes;
    msgpack would copy each into a bytes object). A payload this reader refuses (another type's
    fields, a value of an unexpected form, not msgpack) is read by :func:`_unpack` and the checks
    after it, which name what is wrong."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or not VIEW_MIN_BYTES <= len(payload) <= max_bytes:
        return _unpack(payload, max_bytes)  # no array in it long enough for a view
    try:
        s = _view_decoder(cls).decode(payload)
    except Exception:  # noqa: BLE001 - msgspec raises several types on garbage (bad UTF-8 among them)
        return _unpack(payload, max_bytes)
    env: dict[str, Any] = {}
    rest = []
    direct = cls.DIRECT_ARRAYS
    for n in s.__struct_fields__:
        v = getattr(s, n)
        t = type(v)
        if t is _WireArray:
            v = _wire_map(v, direct)
        elif t is dict and v and type(next(iter(v.values()))) is _WireArray:
            v = {k: _wire_map(w, direct) for k, w in v.items()}
        elif t not in _PLAIN:
            if v is msgspec.UNSET:
                continue
            rest.append(v)
        env[n] = v
    if rest and not _as_msgpack_reads(rest):
        return _unpack(payload, max_bytes)
    _check_envelope(env)
    return env


_PLAIN = (type(None), bool, int, float, str, bytes)


def _as_msgpack_reads(values: list[Any]) -> bool:
    """Whether ``values`` (as msgspec read them) are what msgpack's reader would have given:
    plain values, lists, and maps with string keys only (msgpack refuses other keys; msgspec
    reads extension types and timestamps into other types)."""
    stack = values
    while stack:
        v = stack.pop()
        t = type(v)
        if t in _PLAIN:
            continue
        if t is list:
            stack.extend(v)
        elif t is dict:
            for k, x in v.items():
                if type(k) is not str:
                    return False
                stack.append(x)
        else:
            return False
    return True


class _TransitionsEnvelope(msgspec.Struct, forbid_unknown_fields=True):
    """A :class:`TransitionBatch` as every honest actor sends it, typed field by field for
    :func:`_decode_transitions_plain`; a message of any other form fails to read as this and
    goes the general way."""

    v: int
    t: str
    actor_id: str
    policy_version: int
    seq: int
    data: dict[str, _WireArray]
    priorities: Union[_WireArray, None] = None
    frames: Union[dict[str, _WireArray], None] = None
    frame_base: Union[int, None] = None


_TRANSITIONS_DECODER = msgspec.msgpack.Decoder(_TransitionsEnvelope)


def _plain_array(w: _WireArray) -> np.ndarray | None:
    """A plain wire array (known dtype, at most MAX_NDIM dimensions whose bytes the data holds
    exactly, not empty, not compressed) as the array :func:`decode_array` would make of it; None
    for any other (the general decoder then words what is wrong)."""
    if w.codec is not msgspec.UNSET or w.size is not msgspec.UNSET:
        return None
    dt = _DTYPES.get(w.dtype)
    shape = w.shape
    if dt is None or len(shape) > MAX_NDIM:
        return None
    data = w.data
    n = dt.itemsize
    for d in shape:
        if d < 0:
            return None
        n *= d
    if not n or n != len(data):
        return None
    if n < VIEW_MIN_BYTES or w.dtype != "uint8":
        data = bytes(data)  # aligned, and cheaper than a view on a short array
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _plain_arrays(m: dict[str, _WireArray]) -> dict[str, np.ndarray] | None:
    if not m or len(m) > MAX_FIELDS:
        return None
    out = {}
    for k, w in m.items():
        try:
            _check_field_name("", k)
        except ProtocolError:
            return None
        a = _plain_array(w)
        if a is None:
            return None
        out[k] = a
    return out


def _decode_transitions_plain(payload: Any, max_bytes: int) -> "TransitionBatch | None":
    """The short way to a :class:`TransitionBatch` (every chunk an honest actor sends): the
    envelope read by one typed msgspec decoder, the arrays made straight from its views, then
    the message's own checks (:meth:`TransitionBatch._validate`). None for anything off that
    form (a field of another type, an unknown or missing field, a compressed, empty or
    malformed array, a name or number out of its rule): :meth:`Message.decode` then takes the
    general way, which accepts or refuses it with the reason. It never accepts what the general
    way refuses, and gives the same message for what both accept
    (tests/unit/test_protocol.py compares the two on every mutation of a chunk)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) > max_bytes:
        return None
    try:
        s = _TRANSITIONS_DECODER.decode(payload)
    except Exception:  # noqa: BLE001 - msgspec raises several types; the general way words it
        return None
    if s.v != PROTOCOL_VERSION or s.t != TransitionBatch.TYPE or not _NAME_RE.match(s.actor_id):
        return None
    lo, hi = INT_RANGES["int"]
    if not (lo <= s.policy_version <= hi and 0 <= s.seq <= INT64_MAX):
        return None
    fb = s.frame_base
    if fb is not None and not 0 <= fb <= MAX_FRAME_ID:
        return None
    data = _plain_arrays(s.data)
    if data is None:
        return None
    prio = None
    if s.priorities is not None:
        prio = _plain_array(s.priorities)
        if prio is None:
            return None
    frames = None
    if s.frames is not None:
        frames = _plain_arrays(s.frames)
        if frames is None:
            return None
    msg = TransitionBatch(s.actor_id, s.policy_version, s.seq, data, prio, frames, fb)
    msg._validate()  # raises ProtocolError: refused here as the general way would refuse it
    return msg


def decode_any(payload: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, limits: DecodeLimits | None = None) -> Message:
    """Decode a message of any registered type."""
    env = _unpack(payload, max_bytes)
    cls = _REGISTRY.get(env["t"])
    if cls is None:
        raise ProtocolError("t", f"unknown message type {env['t']!r:.100}", "type")
    return cls._from_envelope(env, limits or _DEFAULT_LIMITS)





_ARRAY_FIELDS: dict[type, tuple[tuple[str, bool], ...]] = {}


def _array_fields(cls: type["Message"]) -> tuple[tuple[str, bool], ...]:
    """``(field, is a map of arrays)`` of the array fields of ``cls``, built once per class."""
    out = _ARRAY_FIELDS.get(cls)
    if out is None:
        out = _ARRAY_FIELDS[cls] = tuple((n, k.startswith("arrays")) for n, k in cls.SCHEMA.items() if k.startswith("array"))
    return out


def _check_declared(cls: type["Message"], env: dict[str, Any], limits: DecodeLimits) -> None:
    """The compressed arrays of a message, from their declared numbers alone (nothing is
    decompressed): each header is sane, allowed by the receiver's spec (``limits.packed``), and
    together they declare at most ``limits.max_decoded_bytes``. Maps too malformed to read are
    left to the full decoder, which refuses them."""
    total = 0
    for n, many in _array_fields(cls):
        v = env.get(n)
        if type(v) is not dict:
            continue
        if many:
            if len(v) > MAX_FIELDS:
                raise ProtocolError(n, f"has {len(v)} arrays, more than {MAX_FIELDS}", "size")
            items = v.items()
        else:
            items = ((None, v),)
        for k, m in items:
            if type(m) is not dict or len(m) != 5 or m.keys() != _PACKED_KEYS:
                continue
            path = n if k is None else f"{n}.{str(k)[:128]}"
            size = _check_packed_header(path, m)
            if limits.packed is not None:
                allowed = limits.packed.get(path)
                if allowed is None:
                    raise ProtocolError(path, "is compressed, but the receiver's spec has no uint8 field by that name; "
                                        "refused unread", "spec")
                if tuple(m["shape"][1:]) not in allowed:
                    raise ProtocolError(path, f"declares rows of {m['shape'][1:]}, the receiver's spec says "
                                        f"{' or '.join(str(list(a)) for a in allowed)}; refused unread", "spec")
            total += size
            if total > limits.max_decoded_bytes:
                raise ProtocolError(path, f"the compressed arrays declare more than {limits.max_decoded_bytes} "
                                    "decoded bytes together; refused unread", "size")


def _check(name: str, kind: str, v: Any, rng: tuple[int, int] | None = None) -> Any:
    optional = kind.endswith("?")
    base = kind.rstrip("?")
    if v is None:
        if optional:
            return None
        raise ProtocolError(name, "must not be nil", "field")
    if base in ("int", "uint"):
        lo, hi = rng or INT_RANGES[base]
        if type(v) is not int or not lo <= v <= hi:
            raise ProtocolError(name, f"must be an integer in {lo}..{hi}, got {v!r:.100}", "field")
        return v
    if base == "float":
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ProtocolError(name, f"must be a finite number, got {v!r}", "nonfinite" if isinstance(v, float) else "field")
        return float(v)
    if base == "bool":
        if not isinstance(v, bool):
            raise ProtocolError(name, f"must be a boolean, got {v!r}", "field")
        return v
    if base == "str":
        if not isinstance(v, str) or len(v) > 4096:
            raise ProtocolError(name, "must be a string of at most 4096 characters", "field")
        return v
    if base == "name":
        return check_name(name, v)
    if base == "array":
        return decode_array(name, v)
    if base == "arrays":
        return decode_arrays(name, v)
    if base == "map":
        if not isinstance(v, dict) or len(v) > 1024:
            raise ProtocolError(name, "must be a map of at most 1024 entries", "field")
        for k, x in v.items():
            if not isinstance(k, str) or len(k) > 256 or not (isinstance(x, (int, float, str, bool)) or x is None):
                raise ProtocolError(f"{name}.{str(k)[:100]}", "entries must map strings of at most 256 characters "
                                    "to numbers or strings", "field")
            if isinstance(x, float) and not math.isfinite(x):
                raise ProtocolError(f"{name}.{k}", "must be finite", "nonfinite")
            if type(x) is int and not INT64_MIN <= x <= INT64_MAX:
                raise ProtocolError(f"{name}.{k}", f"{x} is outside the int64 range", "field")
        return v
    raise AssertionError(f"unknown schema kind {kind}")  # programming error, not input


def _require_1d(name: str, a: np.ndarray, kinds: str, n: int | None = None) -> None:
    if a.ndim != 1:
        raise ProtocolError(name, f"must be 1-D, got shape {list(a.shape)}", "shape")
    if a.dtype.kind not in kinds:
        raise ProtocolError(name, f"dtype {a.dtype.name} is not allowed here", "dtype")
    if n is not None and a.shape[0] != n:
        raise ProtocolError(name, f"has {a.shape[0]} entries, expected {n}", "batch")


def _require_finite(name: str, a: np.ndarray, nonneg: bool = False) -> None:
    if not np.isfinite(a).all():
        raise ProtocolError(name, "contains NaN or Inf", "nonfinite")
    if nonneg and (a < 0).any():
        raise ProtocolError(name, "contains negative values", "negative")


def frame_table(field: str) -> str:
    """Frame table a frame-id field reads: ``next_obs/X`` and ``obs/X`` both read ``obs/X``."""
    return field[5:] if field.startswith("next_") else field


@dataclass(frozen=True)
class TransitionBatch(Message):
    """A chunk of B transitions from one actor (Ape-X). ``data``: flat ``{name: array[B, ...]}``
    (for Ape-X: ``obs/*``, ``action``, ``reward`` (n-step discounted sum), ``next_obs/*``,
    ``terminated``, ``truncated``, ``n`` (steps actually summed)); ``priorities``: float32[B] or
    nil (then the replay uses its running max). Float arrays must be finite.

    Frame mode (image envs; both nil otherwise): ``frames`` ``{obs field: array[F, ...]}`` are
    the observation frames this actor records for the first time, with ids ``frame_base ..
    frame_base + F - 1`` (ids count up over the actor's life; every table has F frames, one per
    recorded observation; F may be 0, then ``frame_base`` is the next id). Each data field whose
    :func:`frame_table` is a key of ``frames`` holds frame ids instead of arrays: integer ``[B]``
    (the item is one frame) or ``[B, k]`` (a stack of k frames, oldest first), naming frames of
    this chunk or of the same actor's earlier chunks."""

    TYPE: ClassVar[str] = "transitions"
    DIRECT_ARRAYS: ClassVar[bool] = True
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "name", "policy_version": "int", "seq": "uint",
                                        "data": "arrays", "priorities": "array?", "frames": "arrays?",
                                        "frame_base": "uint?"}
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset({"frames", "frame_base"})
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {"frame_base": (0, MAX_FRAME_ID)}
    actor_id: str
    policy_version: int
    seq: int
    data: dict[str, np.ndarray]
    priorities: np.ndarray | None = None
    frames: dict[str, np.ndarray] | None = None
    frame_base: int | None = None

    @classmethod
    def decode(cls, payload: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
               limits: DecodeLimits | None = None) -> "TransitionBatch":
        """As :meth:`Message.decode`; a chunk of the form every honest actor sends takes a
        shorter way there (:func:`_decode_transitions_plain`, about half the Python work)."""
        msg = _decode_transitions_plain(payload, max_bytes)
        return msg if msg is not None else super().decode(payload, max_bytes, limits)

    def frame_refs(self) -> dict[str, np.ndarray]:
        """The data fields that are frame ids (empty outside frame mode)."""
        return dict(self._frame_refs)

    @cached_property
    def _frame_refs(self) -> dict[str, np.ndarray]:
        # found once per message: the checks and the replay's insert both ask
        if self.frames is None:
            return {}
        return {k: v for k, v in self.data.items() if frame_table(k) in self.frames}

    def frame_id_bounds(self) -> dict[str, tuple[int, int]]:
        """``{field: (smallest id, largest id)}`` of the frame-id fields that hold any id: the
        decode's check finds them, and the replay's insert reads them instead of reducing the
        ids again (a numpy reduction costs microseconds even on a few hundred ids)."""
        return dict(self._id_bounds)

    @cached_property
    def _id_bounds(self) -> dict[str, tuple[int, int]]:
        # a message built here, not decoded: :meth:`_validate_frames` fills this when it runs
        return {k: (int(v.min()), int(v.max())) for k, v in self._frame_refs.items() if v.size}

    @property
    def batch_size(self) -> int:
        return int(next(iter(self.data.values())).shape[0])

    def _validate(self) -> None:
        b = None
        for k, a in self.data.items():
            if a.ndim == 0:
                raise ProtocolError(f"data.{k}", "must have a batch dimension", "shape")
            if b is None:
                b = a.shape[0]
            elif a.shape[0] != b:
                raise ProtocolError(f"data.{k}", f"batch size {a.shape[0]} differs from {b}", "batch")
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ProtocolError(f"data.{k}", "contains NaN or Inf", "nonfinite")
        if b == 0:
            raise ProtocolError("data", "batch is empty", "batch")
        if self.priorities is not None:
            _require_1d("priorities", self.priorities, "f", b)
            _require_finite("priorities", self.priorities, nonneg=True)
        if self.frames is not None or self.frame_base is not None:
            self._validate_frames()

    def _validate_frames(self) -> None:
        if self.frames is None or self.frame_base is None:
            raise ProtocolError("frames", "frames and frame_base come together", "field")
        n_f = None
        for k, a in self.frames.items():
            if a.ndim == 0 or (n_f is not None and a.shape[0] != n_f):
                raise ProtocolError(f"frames.{k}", f"must hold one frame per id ({n_f} in the other tables)", "batch")
            n_f = a.shape[0]
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ProtocolError(f"frames.{k}", "contains NaN or Inf", "nonfinite")
        refs = self.frame_refs()
        if not refs:
            raise ProtocolError("frames", "no data field names a frame table", "field")
        end = self.frame_base + n_f
        if end > MAX_FRAME_ID:
            raise ProtocolError("frame_base", f"frame_base + frames = {end} exceeds {MAX_FRAME_ID}", "field")
        bounds = {}
        for k, ids in refs.items():
            if ids.dtype != np.int64 or ids.ndim not in (1, 2, 3):  # [B, m+1, k]: R2D2 sequences of stacks
                raise ProtocolError(f"data.{k}", f"frame ids must be int64 [B], [B, k], [B, m+1] or [B, m+1, k], "
                                                 f"got {ids.dtype.name}{list(ids.shape)}", "dtype")
            if ids.size:
                lo, hi = int(ids.min()), int(ids.max())
                if lo < 0 or hi >= end:
                    raise ProtocolError(f"data.{k}", f"frame ids must be in [0, {end}) (frame_base + frames)", "field")
                bounds[k] = (lo, hi)
        self.__dict__["_id_bounds"] = bounds  # what frame_id_bounds() answers: found once


@dataclass(frozen=True)
class SampleRequest(Message):
    """Learner -> replay (query payload): sample ``batch_size`` items with IS exponent ``beta``."""

    TYPE: ClassVar[str] = "sample_request"
    SCHEMA: ClassVar[dict[str, str]] = {"request_id": "uint", "batch_size": "uint", "beta": "float"}
    request_id: int
    batch_size: int
    beta: float

    def _validate(self) -> None:
        if not 1 <= self.batch_size <= MAX_SAMPLE_BATCH:
            raise ProtocolError("batch_size", f"{self.batch_size} is outside 1..{MAX_SAMPLE_BATCH}", "field")
        if not 0.0 <= self.beta <= 1.0:
            raise ProtocolError("beta", f"{self.beta} is outside [0, 1]", "field")


@dataclass(frozen=True)
class SampleReply(Message):
    """Replay -> learner (query reply). ``status`` is ``"ok"`` (then ``keys`` int64[B],
    ``probabilities`` float64[B], ``weights`` float32[B] and ``data`` are set) or ``"not_ready"``
    (then ``reason`` says why, e.g. ``"min_size 1000 > size 12"``).

    ``mass`` (optional, a finite float >= 0, in both kinds of reply): the replay's total
    priority mass when it answered, ``sum_i (p_i + eps) ** alpha`` over the items it may sample
    (the live item count in uniform mode), so that ``probabilities`` are ``leaf / mass``; with
    ``replay_size`` it is what a learner sampling across replay shards weighs each shard by
    (:class:`~zenrl.common.replay_client.ShardedReplayClient`). Left out by replays that predate it."""

    TYPE: ClassVar[str] = "sample_reply"
    DIRECT_ARRAYS: ClassVar[bool] = True
    SCHEMA: ClassVar[dict[str, str]] = {"request_id": "uint", "status": "str", "reason": "str",
                                        "replay_size": "uint", "keys": "array?",
                                        "probabilities": "array?", "weights": "array?",
                                        "data": "arrays?", "mass": "float?"}
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset({"mass"})
    request_id: int
    status: str
    reason: str = ""
    replay_size: int = 0
    keys: np.ndarray | None = None
    probabilities: np.ndarray | None = None
    weights: np.ndarray | None = None
    data: dict[str, np.ndarray] | None = None
    mass: float | None = None

    def _validate(self) -> None:
        if self.status not in ("ok", "not_ready"):
            raise ProtocolError("status", f"{self.status!r} is not ok or not_ready", "field")
        if self.mass is not None and not self.mass >= 0.0:
            raise ProtocolError("mass", f"{self.mass!r} must be >= 0", "negative")
        if self.status == "ok":
            if self.keys is None or self.probabilities is None or self.weights is None or self.data is None:
                raise ProtocolError("keys", "an ok reply needs keys, probabilities, weights and data", "field")
            _require_1d("keys", self.keys, "i")
            b = self.keys.shape[0]
            _require_1d("probabilities", self.probabilities, "f", b)
            _require_1d("weights", self.weights, "f", b)
            _require_finite("weights", self.weights, nonneg=True)
            for k, a in self.data.items():
                if a.ndim == 0 or a.shape[0] != b:
                    raise ProtocolError(f"data.{k}", f"batch size differs from {b}", "batch")


@dataclass(frozen=True)
class PriorityUpdate(Message):
    """Learner -> replay: new priorities (|TD error|) for sampled keys, int64[K] and float32[K];
    optional ``poisoned`` int64[P]: keys of sampled items that made the learner's loss or
    gradient non-finite (the replay stops sampling them and charges their source). Keys are
    >= 0 (the replay issues no other)."""

    TYPE: ClassVar[str] = "priorities"
    SCHEMA: ClassVar[dict[str, str]] = {"keys": "array", "priorities": "array", "poisoned": "array?"}
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset({"poisoned"})
    keys: np.ndarray
    priorities: np.ndarray
    poisoned: np.ndarray | None = None

    def _validate(self) -> None:
        _require_1d("keys", self.keys, "i")
        _require_1d("priorities", self.priorities, "f", self.keys.shape[0])
        _require_finite("priorities", self.priorities, nonneg=True)
        if self.keys.size and int(self.keys.min()) < 0:
            raise ProtocolError("keys", f"contains {int(self.keys.min())}; replay keys are >= 0", "negative")
        if self.poisoned is not None:
            _require_1d("poisoned", self.poisoned, "i")
            if self.poisoned.shape[0] > MAX_SAMPLE_BATCH:
                raise ProtocolError("poisoned", f"names {self.poisoned.shape[0]} keys, more than {MAX_SAMPLE_BATCH}", "size")
            if self.poisoned.size and int(self.poisoned.min()) < 0:
                raise ProtocolError("poisoned", f"contains {int(self.poisoned.min())}; replay keys are >= 0", "negative")


@dataclass(frozen=True)
class Weights(Message):
    """Learner -> actors: network parameters ``params`` (``{name: array}``, the torch
    ``state_dict`` names) at ``version`` (strictly increasing over the run, also across resumes).
    ``arch`` is a fingerprint of the network's shapes so a mismatched actor refuses them."""

    TYPE: ClassVar[str] = "weights"
    SCHEMA: ClassVar[dict[str, str]] = {"version": "uint", "learner_id": "name", "arch": "str",
                                        "updates": "uint", "params": "arrays"}
    version: int
    learner_id: str
    arch: str
    updates: int
    params: dict[str, np.ndarray]

    def _validate(self) -> None:
        for k, a in self.params.items():
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ProtocolError(f"params.{k}", "contains NaN or Inf", "nonfinite")


@dataclass(frozen=True)
class Gradients(Message):
    """A3C worker -> learner: gradients of the loss w.r.t. each parameter (``{name: array}`` with
    the parameter's shape) computed from parameters at ``version``, over ``steps`` env steps."""

    TYPE: ClassVar[str] = "gradients"
    SCHEMA: ClassVar[dict[str, str]] = {"worker_id": "name", "version": "uint", "steps": "uint",
                                        "grads": "arrays"}
    worker_id: str
    version: int
    steps: int
    grads: dict[str, np.ndarray]

    def _validate(self) -> None:
        for k, a in self.grads.items():
            if a.dtype.kind != "f":
                raise ProtocolError(f"grads.{k}", f"dtype {a.dtype.name} is not a float", "dtype")
            if not np.isfinite(a).all():
                raise ProtocolError(f"grads.{k}", "contains NaN or Inf", "nonfinite")


@dataclass(frozen=True)
class EpisodeStats(Message):
    """Actor -> anyone: finished episodes since the last message. float32[K] returns,
    int32/int64[K] lengths; ``env_steps`` is the actor's total env steps so far."""

    TYPE: ClassVar[str] = "episodes"
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "name", "slot": "int", "epsilon": "float",
                                        "policy_version": "int", "env_steps": "uint",
                                        "returns": "array", "lengths": "array"}
    actor_id: str
    slot: int
    epsilon: float
    policy_version: int
    env_steps: int
    returns: np.ndarray
    lengths: np.ndarray

    def _validate(self) -> None:
        _require_1d("returns", self.returns, "f")
        _require_finite("returns", self.returns)
        _require_1d("lengths", self.lengths, "iu", self.returns.shape[0])


@dataclass(frozen=True)
class EvalResult(Message):
    """Evaluator -> anyone: greedy episodes played with weights ``version``. returns float32[K];
    outcomes int8[K] (+1 win, 0 draw, -1 loss) for match envs, nil otherwise."""

    TYPE: ClassVar[str] = "eval"
    SCHEMA: ClassVar[dict[str, str]] = {"version": "int", "updates": "uint", "returns": "array", "outcomes": "array?"}
    version: int
    updates: int
    returns: np.ndarray
    outcomes: np.ndarray | None = None

    def _validate(self) -> None:
        _require_1d("returns", self.returns, "f")
        _require_finite("returns", self.returns)
        if self.outcomes is not None:
            _require_1d("outcomes", self.outcomes, "i", self.returns.shape[0])
            if self.outcomes.size and (self.outcomes.min() < -1 or self.outcomes.max() > 1):
                raise ProtocolError("outcomes", "must be -1 (loss), 0 (draw) or +1 (win)", "field")


@dataclass(frozen=True)
class Stats(Message):
    """Any process -> anyone: a flat map of numbers/strings (rates, counters, sizes)."""

    TYPE: ClassVar[str] = "stats"
    SCHEMA: ClassVar[dict[str, str]] = {"role": "name", "id": "name", "time": "float", "values": "map"}
    role: str
    id: str
    time: float
    values: dict[str, Any] = field(default_factory=dict)


#: Most steps one Unroll may carry, and most actions its behaviour logits may have.
MAX_UNROLL_STEPS = 4096
MAX_UNROLL_ACTIONS = 65536
#: Cap on the decoded size of one Unroll's observation arrays (``obs`` and ``final_obs``, the
#: ones that may be compressed), checked from the declared shapes before anything is
#: decompressed; the other arrays travel raw, bound by the message cap.
MAX_UNROLL_BYTES = 256 * 1024 * 1024
#: Largest magnitude of an Unroll's integers (policy_version, seq): they fit a signed int64.
MAX_UNROLL_INT = (1 << 63) - 1

_UNROLL_STEP_FIELDS = {"action": "int64", "behaviour_logp": "float32", "reward": "float32",
                       "terminated": "bool", "truncated": "bool"}


@dataclass(frozen=True)
class Unroll(Message):
    """IMPALA actor -> learner: T consecutive steps of one env, acted with the actor's policy at
    ``policy_version`` (-1 before it received any weights); ``seq`` counts the actor's unrolls.

    ``obs``: ``{"obs" or "obs/<key>": array[T+1, ...]}``, the observations acted on at steps
    0..T-1, then the one after the last step (the bootstrap observation; where step T-1 ended an
    episode it is the next episode's first). ``action`` int64[T], or float32[T, d] for continuous
    actions (a d-dimensional ``Box``, normalised to [-1, 1]: the sampled action, before the env
    clips it); ``behaviour_logp`` float32[T] (log mu(a_t|x_t), a log-density for continuous
    actions); ``reward`` float32[T]; ``terminated``, ``truncated`` bool[T].
    ``final_obs``: ``{same names: array[K, ...]}``, the true final observations of the K steps
    with ``truncated & ~terminated``, in step order (the learner bootstraps from them; the
    unroll's next row is already the reset observation); nil or 0-row arrays when K = 0.
    ``behaviour_logits``: float32[T, A] or nil (lets a learner compute KL or full-distribution
    corrections). Float arrays must be finite. uint8 observation arrays may be lz4-compressed.

    Frame mode (frame-stacked image fields; nil otherwise): ``frames`` ``{field: array[F, ...]}``
    holds the distinct frames of this unroll's stacks of that field, each once; ``obs[field]``
    is then int64[T+1, k] and ``final_obs[field]`` int64[K, k], the frame ids (rows of
    ``frames[field]``, oldest first) of each k-frame stack. Ids are local to the message (an
    unroll stands alone: the learner may drop any). :meth:`resolved` gives the unroll with the
    stacks rebuilt, ``array[rows, k, ...]``.

    Decoding checks, before decompressing anything: the steps T (from ``action``'s declared
    shape) are 1..MAX_UNROLL_STEPS, every ``obs`` array declares T+1 rows, and the observation
    arrays' declared sizes (frame-mode fields as rebuilt) together stay under MAX_UNROLL_BYTES.
    ``decode(..., spec=...)`` also checks every declared observation dtype and item shape
    against the env's (:meth:`check_declared`) before decompressing."""

    TYPE: ClassVar[str] = "unroll"
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "name", "policy_version": "int", "seq": "uint",
                                        "obs": "arrays", "action": "array", "behaviour_logp": "array",
                                        "reward": "array", "terminated": "array", "truncated": "array",
                                        "final_obs": "arrays?", "behaviour_logits": "array?", "frames": "arrays?"}
    OMIT_NONE: ClassVar[frozenset[str]] = frozenset({"frames"})
    actor_id: str
    policy_version: int
    seq: int
    obs: dict[str, np.ndarray]
    action: np.ndarray
    behaviour_logp: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    final_obs: dict[str, np.ndarray] | None = None
    behaviour_logits: np.ndarray | None = None
    frames: dict[str, np.ndarray] | None = None

    @property
    def steps(self) -> int:
        """T, the number of steps."""
        return int(self.action.shape[0])

    @property
    def cut(self) -> np.ndarray:
        """bool[T]: the steps whose final observation is in ``final_obs`` (truncated, not terminated)."""
        return self.truncated & ~self.terminated

    @property
    def nbytes(self) -> int:
        """Bytes of all arrays once decoded (what the learner's queue holds)."""
        arrays = [*self.obs.values(), *(self.final_obs or {}).values(), self.action, self.behaviour_logp,
                  self.reward, self.terminated, self.truncated]
        if self.behaviour_logits is not None:
            arrays.append(self.behaviour_logits)
        arrays += (self.frames or {}).values()
        return sum(int(a.nbytes) for a in arrays)

    def framed(self, fields: Iterable[str]) -> "Unroll":
        """The frame-mode form of this unroll (:meth:`resolved` inverts it): the ``fields``
        present, k-frame stacks ``array[rows, k, ...]`` (oldest first, as gymnasium's
        FrameStackObservation gives), as their distinct frames and int64 ids. The stacks are
        walked in time order (each truncated step's final observation after its row); a slot
        reuses the frame of the previous stack's next slot, or of its own next slot, where
        every field's content is equal (a continuing episode, or reset padding), else it is a
        new frame. Equal content is what makes a reuse correct: no episode boundary is read."""
        names = [f for f in fields if f in self.obs]
        if not names or self.frames is not None:
            return self
        ks = {self.obs[f].shape[1] if self.obs[f].ndim >= 3 else 0 for f in names}
        if len(ks) != 1 or 0 in ks:
            raise ValueError(f"frame fields {names} must be stacks [rows, k, ...] of one k, got {ks}")
        k = ks.pop()
        fin = self.final_obs or {}
        src = {"obs": self.obs, "final_obs": fin}
        ids = {"obs": np.empty((self.steps + 1, k), np.int64),
               "final_obs": np.empty((int(self.cut.sum()), k), np.int64)}
        order, j = [], 0
        for t, c in enumerate(np.append(self.cut, False)):
            order.append(("obs", t))
            if c:
                order.append(("final_obs", j))
                j += 1
        picked: list[tuple[str, int, int]] = []  # (group, row, slot) of each new frame
        prev: tuple[str, int] | None = None
        for g, r in order:
            cur = {f: src[g][f][r] for f in names}
            row = ids[g][r]
            before = None if prev is None else ({f: src[prev[0]][f][prev[1]] for f in names}, ids[prev[0]][prev[1]])
            slots: Iterable[int] = range(k - 1, -1, -1)
            if before is not None and all(np.array_equal(cur[f][:-1], before[0][f][1:]) for f in names):
                row[:-1] = before[1][1:]  # a continuing episode: only the newest slot is left
                slots = (k - 1,)
            for i in slots:
                if i < k - 1:
                    if before is not None and all(np.array_equal(cur[f][i], before[0][f][i + 1]) for f in names):
                        row[i] = before[1][i + 1]
                        continue
                    if all(np.array_equal(cur[f][i], cur[f][i + 1]) for f in names):
                        row[i] = row[i + 1]
                        continue
                picked.append((g, r, i))
                row[i] = len(picked) - 1
            prev = (g, r)
        frames = {f: np.stack([src[g][f][r][i] for g, r, i in picked]) for f in names}
        obs = {**self.obs, **{f: ids["obs"] for f in names}}
        final = {**fin, **{f: ids["final_obs"] for f in names}} if self.final_obs is not None else None
        return replace(self, obs=obs, final_obs=final, frames=frames)

    def resolved(self) -> "Unroll":
        """This unroll with every frame-mode field rebuilt from its frames:
        ``frames[f][ids]`` -> ``array[rows, k, ...]`` (itself when not in frame mode)."""
        if self.frames is None:
            return self
        obs, fin = dict(self.obs), dict(self.final_obs) if self.final_obs is not None else None
        for k, fr in self.frames.items():
            obs[k] = fr[obs[k]]
            if fin is not None:
                fin[k] = fr[fin[k]]
        return replace(self, obs=obs, final_obs=fin, frames=None)

    @classmethod
    def decode(cls, payload: bytes, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
               limits: DecodeLimits | None = None,
               spec: Mapping[str, tuple[str, tuple[int, ...]]] | None = None) -> "Unroll":
        """As :meth:`Message.decode`; with ``spec`` (observation field -> (dtype, item shape),
        the env's), the declared observation arrays are checked against it first
        (:meth:`check_declared`), before anything is decompressed."""
        env = _unpack_views(cls, payload, max_bytes)
        if env["t"] != cls.TYPE:
            raise ProtocolError("t", f"expected message type {cls.TYPE!r:.100}, got {env['t']!r:.100}", "type")
        if spec is not None:
            cls.check_declared(env, spec)
        return cls._from_envelope(env, limits or _DEFAULT_LIMITS)  # type: ignore[return-value]

    @staticmethod
    def check_declared(env: dict[str, Any], spec: Mapping[str, tuple[str, tuple[int, ...]]]) -> None:
        """The observation fields of an unpacked Unroll against the env's ``spec``, from the
        declared ``dtype``/``shape`` alone: the same field names; each plain array's dtype and
        item shape the spec's; each frame-mode field's frames of the spec's dtype and frame shape
        (the spec's item shape less its first, stack axis) with ids [rows, spec's k]. A lying
        sender is refused (reason ``spec``) before its arrays are decompressed."""
        frames = env.get("frames")
        frames = frames if type(frames) is dict else {}
        for group in ("obs", "final_obs", "frames"):
            maps = env.get(group)
            if maps is None and group != "obs":
                continue
            if type(maps) is not dict or not set(maps) <= set(spec) or (group == "obs" and set(maps) != set(spec)):
                names = sorted(maps) if type(maps) is dict else maps
                raise ProtocolError(group, f"fields {names!r} are not the env's {sorted(spec)}", "spec")
            for k, m in maps.items():
                dtype, item = spec[k]
                got = (m.get("dtype"), m.get("shape")) if type(m) is dict else (None, None)
                if group != "frames" and k in frames:  # frame ids of k-frame stacks
                    if type(got[1]) is not list or len(got[1]) != 2 or got[1][1:] != list(item[:1]):
                        raise ProtocolError(f"{group}.{k}", f"frame ids declare shape {got[1]!r}; the env's "
                                            f"{list(item)} stacks need [rows, {item[0] if item else '?'}]", "spec")
                    continue
                want = list(item[1:]) if group == "frames" else list(item)
                if got[0] != dtype or type(got[1]) is not list or got[1][1:] != want:
                    raise ProtocolError(f"{group}.{k}", f"declares {got[0]}{got[1]!r}; the env's spec needs "
                                        f"{dtype}[rows, {', '.join(map(str, want))}]", "spec")

    @staticmethod
    def _precheck(env: dict[str, Any]) -> None:
        """Declared T and sizes, read from the array maps' ``shape``/``size`` entries alone
        (maps too malformed to read are left to the full decoder, which refuses them)."""
        def shape_of(m: Any) -> list[int] | None:
            if type(m) is dict and type(m.get("shape")) is list:
                declared_elements("array", m["shape"])  # bounded dimensions, or ProtocolError
                return m["shape"]
            return None

        act = shape_of(env.get("action"))
        if act is None or len(act) not in (1, 2):  # [T], or [T, d] continuous
            return
        T = act[0]
        if not 1 <= T <= MAX_UNROLL_STEPS:
            raise ProtocolError("action", f"declares {T} steps, outside 1..{MAX_UNROLL_STEPS}", "batch" if T == 0 else "size")
        def nbytes(m: dict[str, Any], shape: list[int]) -> int:
            dt = _DTYPES.get(m.get("dtype")) if type(m.get("dtype")) is str else None
            return math.prod(shape) * (1 if dt is None else dt.itemsize)

        # frame-mode fields: bytes per frame, so that rebuilt stacks count at their full size
        frame_bytes = {}
        frames = env.get("frames")
        for k, m in (frames.items() if type(frames) is dict else ()):
            shape = shape_of(m)
            if shape:
                frame_bytes[k] = nbytes(m, shape[1:])
        total = 0
        for group in ("frames", "obs", "final_obs"):
            maps = env.get(group)
            if type(maps) is not dict or len(maps) > MAX_FIELDS:
                continue  # left to the full decoder
            for k, m in maps.items():
                shape = shape_of(m)
                if shape is None:
                    continue
                if group == "obs" and (not shape or shape[0] != T + 1):
                    raise ProtocolError(f"obs.{k}", f"declares {shape[:1]} rows; an unroll of {T} steps needs {T + 1}", "batch")
                total += nbytes(m, shape)
                if group != "frames" and k in frame_bytes:  # ids [rows, k] -> rows * k frames
                    total += math.prod(shape) * frame_bytes[k]
                if total > MAX_UNROLL_BYTES:
                    raise ProtocolError(f"{group}.{k}", f"declared sizes exceed {MAX_UNROLL_BYTES} bytes; refused unread", "size")

    def _validate(self) -> None:
        if not -1 <= self.policy_version <= MAX_UNROLL_INT:
            raise ProtocolError("policy_version", f"{self.policy_version} is outside -1..2^63-1", "field")
        if self.seq > MAX_UNROLL_INT:
            raise ProtocolError("seq", f"{self.seq} is outside 0..2^63-1", "field")
        T = self.action.shape[0] if self.action.ndim in (1, 2) else -1
        for k, dt in _UNROLL_STEP_FIELDS.items():
            a = getattr(self, k)
            if k == "action" and a.ndim == 2:  # continuous: float32[T, d]
                if a.dtype != np.float32 or not 1 <= a.shape[1] <= MAX_UNROLL_ACTIONS:
                    raise ProtocolError(k, f"must be int64[T], or float32[T, d] with d in 1..{MAX_UNROLL_ACTIONS} "
                                           f"(continuous), got {a.dtype.name}{list(a.shape)}", "shape")
                if not np.isfinite(a).all():
                    raise ProtocolError(k, "contains NaN or Inf", "nonfinite")
                continue
            if a.ndim != 1:
                raise ProtocolError(k, f"must be 1-D [T], got shape {list(a.shape)}", "shape")
            if a.dtype != np.dtype(dt):
                raise ProtocolError(k, f"must be {dt}, got {a.dtype.name}", "dtype")
            if a.shape[0] != T:
                raise ProtocolError(k, f"has {a.shape[0]} steps, action has {T}", "batch")
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ProtocolError(k, "contains NaN or Inf", "nonfinite")
        items = {}
        for k, a in self.obs.items():
            if k != "obs" and not k.startswith("obs/"):
                raise ProtocolError(f"obs.{k}", "observation fields are named obs or obs/<key>", "field")
            # T in 1..MAX_UNROLL_STEPS and T + 1 rows per obs array: checked by _precheck
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise ProtocolError(f"obs.{k}", "contains NaN or Inf", "nonfinite")
            items[k] = (a.dtype, a.shape[1:])
        K = int(self.cut.sum())
        fin = self.final_obs
        if fin is None:
            if K:
                raise ProtocolError("final_obs", f"missing; {K} steps are truncated", "field")
        else:
            if fin.keys() != items.keys():
                raise ProtocolError("final_obs", f"fields {sorted(fin)} differ from obs {sorted(items)}", "field")
            for k, a in fin.items():
                if a.dtype != items[k][0]:
                    raise ProtocolError(f"final_obs.{k}", f"dtype {a.dtype.name} differs from obs {items[k][0].name}", "dtype")
                if a.shape[1:] != items[k][1]:
                    raise ProtocolError(f"final_obs.{k}", f"item shape {list(a.shape[1:])} differs from obs {list(items[k][1])}", "shape")
                if a.shape[0] != K:
                    raise ProtocolError(f"final_obs.{k}", f"has {a.shape[0]} rows for {K} truncated steps", "batch")
                if a.dtype.kind == "f" and not np.isfinite(a).all():
                    raise ProtocolError(f"final_obs.{k}", "contains NaN or Inf", "nonfinite")
        if self.frames is not None:
            self._validate_frames()
        lg = self.behaviour_logits
        if lg is not None:
            if lg.ndim != 2 or lg.shape[0] != T:
                raise ProtocolError("behaviour_logits", f"must be [T={T}, A], got {list(lg.shape)}", "batch")
            if not 1 <= lg.shape[1] <= MAX_UNROLL_ACTIONS:
                raise ProtocolError("behaviour_logits", f"{lg.shape[1]} actions, outside 1..{MAX_UNROLL_ACTIONS}", "shape")
            if lg.dtype != np.float32:
                raise ProtocolError("behaviour_logits", f"must be float32, got {lg.dtype.name}", "dtype")
            if not np.isfinite(lg).all():
                raise ProtocolError("behaviour_logits", "contains NaN or Inf", "nonfinite")

    def _validate_frames(self) -> None:
        """Frame mode: every frames table names an observation field whose ids (and final
        observations' ids) are int64 [rows, k >= 1] rows of that table."""
        for k, fr in self.frames.items():
            if k not in self.obs:
                raise ProtocolError(f"frames.{k}", "names no observation field", "field")
            if fr.ndim < 1:
                raise ProtocolError(f"frames.{k}", "must be [F, ...] frames", "shape")
            if fr.dtype.kind == "f" and not np.isfinite(fr).all():
                raise ProtocolError(f"frames.{k}", "contains NaN or Inf", "nonfinite")
            F = fr.shape[0]
            for group, ids in (("obs", self.obs[k]), ("final_obs", (self.final_obs or {}).get(k))):
                if ids is None:
                    continue
                if ids.dtype != np.int64 or ids.ndim != 2 or ids.shape[1] < 1:
                    raise ProtocolError(f"{group}.{k}", f"frame ids must be int64 [rows, k >= 1], got "
                                        f"{ids.dtype.name}{list(ids.shape)}", "dtype")
                if ids.size and (int(ids.min()) < 0 or int(ids.max()) >= F):
                    raise ProtocolError(f"{group}.{k}", f"frame ids must be in [0, {F}) (the frames sent)", "field")


# --------------------------------------------------------------------------------------------
# League (``zenrl league``, docs/protocol.md "League"): keys under ``zenrl/<league run>/league/``
# --------------------------------------------------------------------------------------------
#: Largest |version| a league message may carry (fits a signed int64).
MAX_LEAGUE_INT = (1 << 63) - 1
#: Largest score a match result may report (the Burger War match has 23 points at most).
MAX_MATCH_SCORE = 1000
#: Kinds of league player.
LEAGUE_KINDS = ("bot", "frozen", "snapshot", "learner")


class LeagueKeys:
    """Key expressions of a league (the run id of ``zenrl league``, which for ``zenrl run`` is
    the launch's own run id; each learning agent's processes have a run id of their own).

    ================================  ===========  =================================================
    key                               kind         message
    ================================  ===========  =================================================
    ``league/opponent``               queryable    :class:`OpponentRequest` -> :class:`OpponentReply`
    ``league/weights``                queryable    :class:`PlayerWeightsRequest` -> :class:`PlayerWeights`
    ``league/table``                  queryable    (empty) -> :class:`LeagueTable`
    ``league/results/<actor>``        put          :class:`MatchResult`     actor -> league
    ================================  ===========  =================================================
    """

    def __init__(self, run_id: str) -> None:
        self.run_id = check_name("run_id", run_id)
        self.prefix = f"zenrl/{run_id}/league"

    @property
    def opponent(self) -> str:
        return f"{self.prefix}/opponent"

    @property
    def weights(self) -> str:
        return f"{self.prefix}/weights"

    @property
    def table(self) -> str:
        return f"{self.prefix}/table"

    def results(self, actor_id: str) -> str:
        return f"{self.prefix}/results/{check_name('actor_id', actor_id)}"

    @property
    def results_all(self) -> str:
        return f"{self.prefix}/results/*"


def _league_int(name: str, v: int, lo: int = -1) -> None:
    if not lo <= v <= MAX_LEAGUE_INT:
        raise ProtocolError(name, f"{v} is outside {lo}..2^63-1", "field")


@dataclass(frozen=True)
class OpponentRequest(Message):
    """Actor -> league (query): the next opponent of learning player ``player``."""

    TYPE: ClassVar[str] = "opponent_request"
    SCHEMA: ClassVar[dict[str, str]] = {"player": "name", "actor_id": "name"}
    player: str
    actor_id: str


@dataclass(frozen=True)
class OpponentReply(Message):
    """League -> actor. ``status`` "ok": play ``opponent`` (``kind`` "bot": the env's bot of that
    name; "snapshot" / "learner": a policy whose weights ``version`` the ``league/weights``
    queryable serves); ``generation``: the requesting player's (an actor reports it back with
    each result). "unknown": ``player`` is no learning agent of this league; "none": nobody can
    be played yet (fall back to a bot); ``reason`` says why. ``kind`` "frozen": the entry of
    that name in the actor's own ``opponents.pool`` (a policy file it loaded itself).
    ``ticket`` (with "ok"): the assignment's number, which the match's :class:`MatchResult`
    cites (league/tickets.py); 0 with any other status. "busy": this actor id asks faster than
    ``league.ticket_rate_per_s``; ask again later."""

    TYPE: ClassVar[str] = "opponent_reply"
    SCHEMA: ClassVar[dict[str, str]] = {"status": "str", "player": "name", "generation": "uint",
                                        "opponent": "str", "kind": "str", "version": "int", "reason": "str",
                                        "ticket": "uint"}
    status: str
    player: str
    generation: int = 0
    opponent: str = ""
    kind: str = ""
    version: int = -1
    reason: str = ""
    ticket: int = 0

    def _validate(self) -> None:
        if self.status not in ("ok", "unknown", "none", "busy"):
            raise ProtocolError("status", f"{self.status!r} is not ok, unknown, none or busy", "field")
        _league_int("generation", self.generation, 0)
        _league_int("version", self.version)
        if self.status == "ok":
            check_name("opponent", self.opponent)
            if self.kind not in LEAGUE_KINDS:
                raise ProtocolError("kind", f"{self.kind!r} is not one of {list(LEAGUE_KINDS)}", "field")


@dataclass(frozen=True)
class PlayerWeightsRequest(Message):
    """Actor -> league (query): the weights of policy player ``player`` at ``version``."""

    TYPE: ClassVar[str] = "player_weights_request"
    SCHEMA: ClassVar[dict[str, str]] = {"player": "name", "version": "int"}
    player: str
    version: int

    def _validate(self) -> None:
        _league_int("version", self.version)


@dataclass(frozen=True)
class PlayerWeights(Message):
    """League -> actor: ``status`` "ok" with the network ``params`` (``{name: array}``, finite,
    the torch ``state_dict`` names) of ``player`` at ``version``, ``arch`` its fingerprint; or
    "missing" (no such player or version now: ``reason``). Also the file format of a stored
    snapshot (``runs/<run>/league/snapshots/<id>.msgpack``)."""

    TYPE: ClassVar[str] = "player_weights"
    SCHEMA: ClassVar[dict[str, str]] = {"status": "str", "player": "name", "version": "int", "updates": "uint",
                                        "arch": "str", "reason": "str", "params": "arrays?"}
    status: str
    player: str
    version: int = -1
    updates: int = 0
    arch: str = ""
    reason: str = ""
    params: dict[str, np.ndarray] | None = None

    def _validate(self) -> None:
        if self.status not in ("ok", "missing"):
            raise ProtocolError("status", f"{self.status!r} is not ok or missing", "field")
        _league_int("version", self.version)
        _league_int("updates", self.updates, 0)
        if self.status == "ok":
            if self.params is None:
                raise ProtocolError("params", "an ok reply needs params", "field")
            for k, a in self.params.items():
                if a.dtype.kind == "f" and not np.isfinite(a).all():
                    raise ProtocolError(f"params.{k}", "contains NaN or Inf", "nonfinite")


@dataclass(frozen=True)
class MatchResult(Message):
    """Actor -> league: one finished match of learning player ``player`` (its ``generation`` as
    the league last told this actor, acting with weights ``player_version``; -1 before any)
    against ``opponent`` (at ``opponent_version``, -1 for a bot); ``outcome`` from ``player``'s
    side: +1 win, 0 draw, -1 loss; the scores as the judge counted them. ``ticket``: the number
    of the assignment this match answers (:class:`OpponentReply`); the league counts a result
    only against an open ticket of this actor for this player, opponent and version, once."""

    TYPE: ClassVar[str] = "match_result"
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "name", "player": "name", "generation": "uint",
                                        "player_version": "int", "opponent": "name", "opponent_version": "int",
                                        "outcome": "int", "my_score": "uint", "enemy_score": "uint",
                                        "ticket": "uint"}
    actor_id: str
    player: str
    generation: int
    player_version: int
    opponent: str
    opponent_version: int
    outcome: int
    my_score: int = 0
    enemy_score: int = 0
    ticket: int = 0

    def _validate(self) -> None:
        if self.outcome not in (-1, 0, 1):
            raise ProtocolError("outcome", f"{self.outcome} must be -1 (loss), 0 (draw) or +1 (win)", "field")
        _league_int("generation", self.generation, 0)
        _league_int("player_version", self.player_version)
        _league_int("opponent_version", self.opponent_version)
        for k in ("my_score", "enemy_score"):
            if getattr(self, k) > MAX_MATCH_SCORE:
                raise ProtocolError(k, f"{getattr(self, k)} exceeds {MAX_MATCH_SCORE}", "field")


@dataclass(frozen=True)
class LeagueTable(Message):
    """League -> ``zenrl league status`` (query reply). ``ids``: the players as a map
    ``{id: index}`` (join order); ``kinds`` / ``roles`` ``{id: str}``, ``versions`` /
    ``generations`` ``{id: int}``; ``counts`` int64[N, N, 3]: wins, draws, losses of row
    player against column player; ``main_pfsp`` ``{id: probability}``: the main agent's
    current opponent distribution; ``values``: league-wide numbers (results, rejections)."""

    TYPE: ClassVar[str] = "league_table"
    SCHEMA: ClassVar[dict[str, str]] = {"ids": "map", "kinds": "map", "roles": "map", "versions": "map",
                                        "generations": "map", "counts": "array", "main_pfsp": "map",
                                        "values": "map"}
    ids: dict[str, Any]
    kinds: dict[str, Any]
    roles: dict[str, Any]
    versions: dict[str, Any]
    generations: dict[str, Any]
    counts: np.ndarray
    main_pfsp: dict[str, Any]
    values: dict[str, Any]

    def _validate(self) -> None:
        n = len(self.ids)
        if sorted(v for v in self.ids.values() if type(v) is int) != list(range(n)):
            raise ProtocolError("ids", "must map the players to 0..N-1", "field")
        if self.counts.shape != (n, n, 3) or self.counts.dtype.kind not in "iu":
            raise ProtocolError("counts", f"must be int[{n}, {n}, 3], got {self.counts.dtype.name}{list(self.counts.shape)}", "shape")
        if self.counts.size and self.counts.min() < 0:
            raise ProtocolError("counts", "contains negative values", "negative")
