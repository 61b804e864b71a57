"""Array specifications shared by the replay storage, the wire protocol and the networks.

A transition is a *flat* mapping ``{field_name: np.ndarray[B, *shape]}``. Nested (dict)
observations are flattened with ``/`` in the field name, e.g. a match-env observation
``{"lidar": float32[360], "pose": float32[4]}`` stored as ``obs`` becomes the fields
``obs/lidar`` and ``obs/pose``. Everything that stores or ships transitions works on such flat
mappings; :func:`flatten` and :func:`unflatten` convert between the two forms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

#: dtypes allowed anywhere in zenrl (storage, wire, checkpoints). Names are numpy's.
ALLOWED_DTYPES = frozenset(
    ["bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "int64", "float16",
     "float32", "float64"]
)

SEP = "/"


@dataclass(frozen=True)
class ArraySpec:
    """Shape and dtype of one field of ONE item (no batch dimension)."""

    shape: tuple[int, ...]
    dtype: str

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
