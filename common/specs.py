"""Array specifications shared by the replay storage, the wire protocol and the networks.

A transition is a *flat* mapping ``{field_name: np.ndarray[B, *shape]}``. Nested (dict)
observations are flattened with ``/`` in the field name, e.g. a match-env observation
``{"lidar": float32[360], "pose": float32[4]}`` stored as ``obs`` becomes the fields
``obs/lidar`` and ``obs/pose``. Everything that stores or ships transitions works on such flat
mappings; :func:`flatten` and :func:`unflatten` convert between the two forms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

#: dtypes allowed anywhere in zenrl (storage, wire, checkpoints). Names are numpy's.
ALLOWED_DTYPES = frozenset(
    ["bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "int64", "float16",
     "float32", "float64"]
)

SEP = "/"

#: Largest ``Discrete`` observation the networks one-hot encode (its first layer holds n x hidden
#: weights); a larger one reaches them as its index, a number.
MAX_CATEGORIES = 4096


@dataclass(frozen=True)
class ArraySpec:
    """Shape and dtype of one field of ONE item (no batch dimension). ``categories``: for an
    observation from a ``Discrete(n, start)`` space, ``(start, n)``: the value names one of n
    categories (the networks one-hot encode it); it says nothing of the storage, so two specs
    that differ only in it compare equal."""

    shape: tuple[int, ...]
    dtype: str
    categories: tuple[int, int] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        dt = np.dtype(self.dtype).name
        if dt not in ALLOWED_DTYPES:
            raise ValueError(f"dtype {self.dtype!r} is not allowed; allowed: {sorted(ALLOWED_DTYPES)}")
        object.__setattr__(self, "dtype", dt)
        shape = tuple(int(s) for s in self.shape)
        if any(s < 0 for s in shape):
            raise ValueError(f"negative dimension in shape {shape}")
        object.__setattr__(self, "shape", shape)

    @property
    def nbytes(self) -> int:
        """Bytes of one item of this field."""
        return int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize


#: A transition spec: field name -> spec of one item.
Spec = Mapping[str, ArraySpec]


def spec_nbytes(spec: Spec) -> int:
    """Bytes of one item of a whole spec."""
    return sum(s.nbytes for s in spec.values())


def spec_of_batch(batch: Mapping[str, np.ndarray]) -> dict[str, ArraySpec]:
    """Spec of the items in a flat batch ``{name: array[B, *shape]}``."""
    return {k: ArraySpec(tuple(v.shape[1:]), v.dtype.name) for k, v in batch.items()}


@dataclass(frozen=True)
class ObsField:
    """One flat observation field of an env, as zenrl ships and stores it: ``spec`` (shape and
    dtype of one item) and its bounds ``low``/``high`` (float64 arrays of ``spec.shape``, +-inf
    where unbounded)."""

    spec: ArraySpec
    low: np.ndarray
    high: np.ndarray


def box_wire_dtype(dtype: Any) -> str:
    """The dtype a ``Box`` observation of ``dtype`` travels and is stored in: uint8 stays (images),
    any other becomes float32."""
    return "uint8" if np.dtype(dtype) == np.uint8 else "float32"


def obs_fields(space: Any, prefix: str = "obs") -> dict[str, ObsField]:
    """The flat observation fields of a gymnasium space (Box, Discrete, or a Dict of those; make_env
    turns a Tuple or a MultiDiscrete into a Dict first):
    ``{"obs": ...}`` or ``{"obs/<key>": ...}``. The one rule for the dtypes on the wire: a uint8
    Box stays uint8 (images), any other Box is float32, a Discrete is int64 (its index, with
    ``categories`` set: the networks one-hot encode it). The networks' input
    spec and the replay's checks are both built from this."""
    import gymnasium as gym  # callers that have an env have gymnasium; this module stays importable without

    if isinstance(space, gym.spaces.Dict):
        out: dict[str, ObsField] = {}
        for k, sub in space.spaces.items():
            out.update(obs_fields(sub, f"{prefix}{SEP}{k}"))
        return out
    if isinstance(space, gym.spaces.Discrete):
        start = int(space.start)
        cats = (start, int(space.n)) if int(space.n) <= MAX_CATEGORIES else None
        return {prefix: ObsField(ArraySpec((), "int64", cats), np.array(start, np.float64),
                                 np.array(start + int(space.n) - 1, np.float64))}
    if isinstance(space, gym.spaces.Box):
        dtype = box_wire_dtype(space.dtype)
        low = np.broadcast_to(np.asarray(space.low, np.float64), space.shape).copy()
        high = np.broadcast_to(np.asarray(space.high, np.float64), space.shape).copy()
        return {prefix: ObsField(ArraySpec(tuple(space.shape), dtype), low, high)}
    raise ValueError(f"observation space {space} is not supported (Box, Discrete, MultiBinary, 1-D MultiDiscrete, or a Dict or Tuple of those)")


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"obs": {"lidar": a, "pose": b}, "action": c}`` -> ``{"obs/lidar": a, "obs/pose": b, "action": c}``."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        name = f"{prefix}{SEP}{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            out.update(flatten(v, name))
        else:
            out[name] = v
    return out


def unflatten(flat: Mapping[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`flatten`."""
    out: dict[str, Any] = {}
    for name, v in flat.items():
        parts = name.split(SEP)
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = v
    return out


@dataclass(frozen=True)
class ObsRule:
    """One observation field: dtype and shape of one item; ``low``/``high`` float64 arrays of
    that shape where a bound is finite (``None`` when no element has a finite bound, or the
    dtype's own range already enforces it, as for uint8 images in [0, 255])."""

    dtype: str
    shape: tuple[int, ...]
    low: np.ndarray | None = None
    high: np.ndarray | None = None


@dataclass(frozen=True)
class Rejection:
    """Why a chunk or an unroll was refused: ``reason`` (a short counter name) and a one-line ``detail``."""

    reason: str
    detail: str


def obs_rules_from_space(space: Any, prefix: str = "obs") -> dict[str, ObsRule]:
    """Rules for the flat observation fields of a gymnasium space (Box, Discrete, Dict of those),
    from :func:`obs_fields` (the dtypes zenrl ships them in)."""
    out: dict[str, ObsRule] = {}
    for name, f in obs_fields(space, prefix).items():
        dtype, shape, low, high = f.spec.dtype, f.spec.shape, f.low, f.high
        if dtype == "uint8" and (low <= 0).all() and (high >= 255).all():
            out[name] = ObsRule(dtype, shape)  # the dtype's own range is the bound
        elif not (np.isfinite(low).any() or np.isfinite(high).any()):
            out[name] = ObsRule(dtype, shape)
        else:
            out[name] = ObsRule(dtype, shape, low, high)
    return out
