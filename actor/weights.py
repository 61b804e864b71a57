"""Following the learner's weights: the newest broadcast taken between steps, never blocking.
Used by every process that acts with the learner's network (Ape-X actors, A3C workers, the
evaluator)."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from zenrl.common import protocol as P
from zenrl.common.errors import ProtocolError, RemoteTimeout
from zenrl.common.networks import arch_fingerprint, arrays_to_params
from zenrl.common.transport import Node

log = logging.getLogger(__name__)

#: largest finite float32: float64 parameters beyond it would load as Inf
FLOAT32_MAX = float(np.finfo(np.float32).max)


class WeightsFollower:
    """Holds the newest :class:`Weights` seen on the broadcast key and loads them into a
    network when asked (``maybe_load``), refusing other architectures and non-finite parameters
    (NaN/Inf are refused when decoded; float64 values beyond float32 here). Never blocks."""

    def __init__(self, node: Node, keys: P.Keys, net: torch.nn.Module, max_bytes: int) -> None:
        self.net = net
        self.arch = arch_fingerprint(net)
        self.version = -1
        self.updates = 0
        self.rejected = 0
        self._max = max_bytes
        self._keys = keys
        self._node = node
        self._latest = node.subscribe_latest(keys.weights)

    def fetch_initial(self, timeout_s: float) -> bool:
        """Ask the learner for its current weights (a restarted actor gets them promptly)."""
        try:
            payload = self._node.query(self._keys.weights_query, None, timeout_s)
        except RemoteTimeout:
            return False
        return self._load(payload)

    def maybe_load(self) -> bool:
        """Load the newest broadcast not yet taken; True if the network changed."""
        payload = self._latest.take()
        return payload is not None and self._load(payload)

    def await_first(self, timeout_s: float) -> bool:
        """True once the network holds the learner's weights: takes the broadcast, else asks the
        learner, else waits for a broadcast, for at most about ``timeout_s`` in all."""
        if self.version >= 0 or self.maybe_load():
            return True
        deadline = time.monotonic() + timeout_s
        if self.fetch_initial(timeout_s):
            return True
        payload = self._latest.wait(max(0.0, deadline - time.monotonic()))
        return payload is not None and self._load(payload)

    def _load(self, payload: bytes) -> bool:
        try:
            w = P.Weights.decode(payload, self._max)
            if w.arch != self.arch:
                raise ProtocolError("arch", f"weights for {w.arch}, this network is {self.arch}", "arch")
            if w.version <= self.version:
                return False
            for k, a in w.params.items():  # float64 beyond float32's range would load as Inf
                if a.dtype.itemsize > 4 and a.dtype.kind == "f" and a.size and float(np.abs(a).max()) > FLOAT32_MAX:
                    raise ProtocolError(f"params.{k}", "has values beyond float32's range (would load as Inf)", "nonfinite")
            arrays_to_params(self.net, w.params)
        except (ProtocolError, ValueError) as e:
            self.rejected += 1
            log.warning("weights rejected: %s", e)
            return False
        self.version, self.updates = w.version, w.updates
        return True
