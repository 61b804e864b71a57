"""``zenrl average``: one policy whose weights are the mean of several checkpoints' weights.

Stochastic weight averaging (Izmailov et al., 2018; for deep RL, Nikishin et al., 2018): the
greedy policy of a value learner can change a lot between checkpoints a few minutes apart, as a
small change in the Q values flips the argmax in many states, while the mean of the weights
along the late part of training sits in a flatter, more stable region. Averaging is done after
training and changes nothing in it; every checkpoint must come from the same run configuration's
network (same algorithm and architecture fingerprint).

The output is a checkpoint file (read with ``torch.load(..., weights_only=True)`` like any other):
the newest input's training state with its policy weights (``policy_path``, e.g. an Ape-X
learner's ``online`` network) replaced by the average, and an ``averaged_from`` list naming the
inputs. Evaluate, export or play it as any checkpoint. It is not meant to resume training from:
the optimizer and target network are the newest input's.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import torch

from zenrl.common.atomic_files import write_atomically
from zenrl.common.checkpoints import list_checkpoints, read_checkpoint
from zenrl.common.errors import ZenrlError


def checkpoints_to_average(sources: Sequence[str | os.PathLike[str]], last: int | None) -> list[Path]:
    """The checkpoint files ``sources`` name, oldest first: files as given, or for a run folder
    (``runs/<id>``) or checkpoints folder its newest ``last`` checkpoints (all of them if None)."""
    if not sources:
        raise ZenrlError("average: name at least one checkpoint file or folder")
    if last is not None and last < 1:
        raise ZenrlError(f"average: --last must be at least 1, not {last}")
    files: list[Path] = []
    for src in sources:
        p = Path(src)
        if p.is_file():
            files.append(p)
        elif p.is_dir():
            folder = p / "checkpoints" if (p / "checkpoints").is_dir() else p
            found = list_checkpoints(folder)
            if not found:
                raise ZenrlError(f"average: no ckpt-*.pt checkpoint in {str(folder)!r}")
            files.extend(found[-last:] if last is not None else found)
        else:
            raise ZenrlError(f"average: {str(p)!r} does not exist (give ckpt-*.pt files, a run folder or its checkpoints folder)")
    if len(set(files)) != len(files):
        raise ZenrlError("average: a checkpoint is named twice")
    return files


def average(sources: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str],
            last: int | None = None) -> dict[str, Any]:
    """Write to ``out`` a checkpoint whose policy weights are the element-wise mean of those of
    the checkpoints ``sources`` name (see :func:`checkpoints_to_average`); returns a summary.
    Floating-point tensors are averaged in float64 and cast back; any other tensor (an integer
    buffer) must be equal in every input and is copied. A file of another algorithm or network,
    or with a non-finite weight, is a :class:`ZenrlError` naming it."""
    files = checkpoints_to_average(sources, last)
    if any(Path(out).resolve() == f.resolve() for f in files):
        raise ZenrlError(f"average: --out {str(out)!r} is one of the checkpoints averaged; write elsewhere")
    states = [(f, read_checkpoint(f)) for f in files]
    newest_file, newest = max(states, key=lambda fs: (fs[1].updates, fs[1].saved_at))
    ref = newest.policy_state()
    sums: dict[str, torch.Tensor] = {}
    for f, st in states:
        if st.algo != newest.algo or st.arch != newest.arch:
            raise ZenrlError(f"average: {f} holds algorithm {st.algo}, network {st.arch}; {newest_file} holds "
                             f"{newest.algo}, {newest.arch}: only one network's checkpoints can be averaged")
        w = st.policy_state()
        if set(w) != set(ref):
            raise ZenrlError(f"average: {f}'s policy has tensors {sorted(set(w) ^ set(ref))} that {newest_file} "
                             "does not share")
        for k, v in w.items():
            if v.shape != ref[k].shape:
                raise ZenrlError(f"average: {f}: {k} has shape {tuple(v.shape)}, {newest_file} {tuple(ref[k].shape)}")
            if v.is_floating_point():
                if not bool(torch.isfinite(v).all()):
                    raise ZenrlError(f"average: {f}: {k} holds a non-finite weight")
                sums[k] = sums[k] + v.double() if k in sums else v.double().clone()
            elif not torch.equal(v, ref[k]):
                raise ZenrlError(f"average: {f}: the integer tensor {k} differs from {newest_file}'s")
    mean = {k: (sums[k] / len(states)).to(ref[k].dtype) if k in sums else ref[k].clone() for k in ref}
    d = newest.to_dict()
    node: Any = d
    for key in newest.policy_path[:-1]:
        node = node[key]
    node[newest.policy_path[-1]] = mean
    d["averaged_from"] = [{"file": f.name, "updates": st.updates} for f, st in states]
    write_atomically(out, lambda fh: torch.save(d, fh))
    return {"out": str(out), "algo": newest.algo, "averaged": len(states),
            "updates": [st.updates for _, st in states], "files": [str(f) for f, _ in states]}
