"""R2D2's recurrent Q-network and the value arithmetic its actors and learners share.

:class:`RecurrentQNetwork`: the feed-forward torsos of :mod:`zenrl.common.networks` (MLP for
vectors, the Nature conv torso for images, one encoder per key of a dict observation, then the
MLP ``network.hidden``), an LSTM, and a dueling head. Its outputs are *rescaled* values
``h(Q)`` (Kapturowski et al., 2019): targets are built as ``h(r + gamma * h_inv(q'))``, which
keeps the regression's scale small whatever the reward scale, without clipping rewards.

Shapes (T steps, B sequences or envs, A actions, H the LSTM size)::

    forward(obs {name: [T, B, ...]}, (h, c) [B, H] each, reset bool[T, B]) -> q [T, B, A], (h, c)
    step(obs {name: [B, ...]}, (h, c), reset bool[B] | None)               -> q [B, A], (h, c)

``reset[t, b]`` marks the first step of an episode: the state is zeroed before that step, so an
unroll with a reset in the middle equals a fresh start there.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from torch import nn

from zenrl.common.config import NetworkConfig
from zenrl.common.networks import NumpyInputs, ObsEncoder, mlp
from zenrl.common.specs import ArraySpec

State = tuple[torch.Tensor, torch.Tensor]


class RecurrentQNetwork(nn.Module):
    """encoder -> MLP ``cfg.hidden`` -> LSTM(``lstm_size``) -> dueling head (``cfg.dueling``)."""

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, cfg: NetworkConfig,
                 lstm_size: int = 128) -> None:
        super().__init__()
        self.encoder = ObsEncoder(spec, cfg.conv)
        self.trunk, d = mlp(self.encoder.out_dim, list(cfg.hidden), cfg.activation)
        self.lstm = nn.LSTM(d, lstm_size)
        self.lstm_size = lstm_size
        self.dueling = cfg.dueling
        if cfg.dueling:
            self.value = nn.Linear(lstm_size, 1)
            self.advantage = nn.Linear(lstm_size, n_actions)
        else:
            self.q = nn.Linear(lstm_size, n_actions)

    def initial_state(self, batch: int, device: torch.device | str = "cpu") -> State:
        """Zero (h, c), float32[B, H] each: the state at an episode's start."""
        z = torch.zeros(batch, self.lstm_size, device=device)
        return z, z.clone()

    def _head(self, y: torch.Tensor) -> torch.Tensor:
        if self.dueling:
            a = self.advantage(y)
            return self.value(y) + a - a.mean(dim=-1, keepdim=True)
        return self.q(y)

    def forward(self, obs: Mapping[str, torch.Tensor], state: State,
                reset: torch.Tensor | None = None) -> tuple[torch.Tensor, State]:
        """Unroll over T steps (see the module docstring for shapes). The LSTM runs as one fused
        call per stretch of steps without a reset (a sequence that never crosses an episode
        boundary has at most one, at t=0), not one call per step."""
        first = next(iter(obs.values()))
        T, B = first.shape[:2]
        x = self.trunk(self.encoder({k: v.reshape(T * B, *v.shape[2:]) for k, v in obs.items()}))
        x = x.reshape(T, B, -1)
        h, c = state
        bounds = [0, T]
        if reset is not None:
            inner = (reset[1:].any(dim=1).nonzero().flatten() + 1).tolist()
            bounds = [0, *inner, T]
        outs = []
        for a, b in zip(bounds[:-1], bounds[1:]):
            if reset is not None:
                keep = (~reset[a]).to(x.dtype).unsqueeze(1)
                h, c = h * keep, c * keep
            y, (h1, c1) = self.lstm(x[a:b], (h.unsqueeze(0), c.unsqueeze(0)))
            h, c = h1[0], c1[0]
            outs.append(y)
        y = outs[0] if len(outs) == 1 else torch.cat(outs, dim=0)
        return self._head(y), (h, c)

    def step(self, obs: Mapping[str, torch.Tensor], state: State,
             reset: torch.Tensor | None = None) -> tuple[torch.Tensor, State]:
        """One batched step for acting: obs ``{name: [B, ...]}`` -> q [B, A] and the new state."""
        x = self.trunk(self.encoder(obs))
        h, c = state
        if reset is not None:
            keep = (~reset).to(x.dtype).unsqueeze(1)
            h, c = h * keep, c * keep
        y, (h1, c1) = self.lstm(x.unsqueeze(0), (h.unsqueeze(0), c.unsqueeze(0)))
        return self._head(y[0]), (h1[0], c1[0])


class NumpyRecurrentQ:
    """A numpy copy of an MLP-only :class:`RecurrentQNetwork`'s :meth:`~RecurrentQNetwork.step`
    for acting on the CPU: flat obs ``{name: array[B, ...]}``, (h, c) float32[B, H] ->
    q float32[B, A], (h, c). The same values as the torch step to float32 rounding, without
    torch's per-op dispatch, which dominates at actor batch sizes (as for
    :class:`zenrl.common.networks.NumpyQ`). :meth:`of` gives None for conv encoders; call
    :meth:`load` after the weights change."""

    def __init__(self, net: RecurrentQNetwork) -> None:
        self.inputs = NumpyInputs(net.encoder)
        self.relu = isinstance(net.trunk[1], nn.ReLU)
        self.load(net)

    @staticmethod
    def of(net: nn.Module) -> "NumpyRecurrentQ | None":
        if not isinstance(net, RecurrentQNetwork) or not NumpyInputs.supports(net.encoder):
            return None
        return NumpyRecurrentQ(net)

    def load(self, net: RecurrentQNetwork) -> None:
        def arr(t: torch.Tensor) -> np.ndarray:
            return np.ascontiguousarray(t.detach().cpu().numpy(), np.float32)

        self.layers = [(arr(m.weight.T), arr(m.bias)) for m in net.trunk if isinstance(m, nn.Linear)]
        # torch's gate order is (i, f, g, o); reordered to (i, f, o, g): one sigmoid over 3H
        H = net.lstm_size
        order = torch.cat([torch.arange(0, 2 * H), torch.arange(3 * H, 4 * H), torch.arange(2 * H, 3 * H)])
        self.w_ih, self.w_hh = arr(net.lstm.weight_ih_l0[order].T), arr(net.lstm.weight_hh_l0[order].T)
        self.b = arr((net.lstm.bias_ih_l0 + net.lstm.bias_hh_l0)[order])
        if net.dueling:  # V + A - mean(A) is linear in the LSTM output: one matrix
            wa, ba = net.advantage.weight.double(), net.advantage.bias.double()
            w = net.value.weight.double() + wa - wa.mean(0, keepdim=True)
            self.head = (arr(w.T.float()), arr((net.value.bias.double() + ba - ba.mean()).float()))
        else:
            self.head = (arr(net.q.weight.T), arr(net.q.bias))

    def __call__(self, flat: Mapping[str, np.ndarray], state: tuple[np.ndarray, np.ndarray],
                 reset: np.ndarray | None = None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        x = self.inputs(flat)
        for w, b in self.layers:
            x = x @ w
            x += b
            if self.relu:
                np.maximum(x, 0.0, out=x)
            else:
                np.tanh(x, out=x)
        h, c = state
        if reset is not None and reset.any():
            h, c = np.where(reset[:, None], 0.0, h), np.where(reset[:, None], 0.0, c)
        H = h.shape[1]
        g = x @ self.w_ih
        g += h @ self.w_hh
        g += self.b
        s = g[:, :3 * H]  # sigmoid(x) = (tanh(x / 2) + 1) / 2, in place: i, f, o
        s *= 0.5
        np.tanh(s, out=s)
        s += 1.0
        s *= 0.5
        np.tanh(g[:, 3 * H:], out=g[:, 3 * H:])
        c = s[:, H:2 * H] * c
        c += s[:, :H] * g[:, 3 * H:]
        h = np.tanh(c)
        h *= s[:, 2 * H:3 * H]
        w, b = self.head
        q = h @ w
        q += b
        return q, (h.astype(np.float32, copy=False), c.astype(np.float32, copy=False))


# --------------------------------------------------------------------------------------------
# Value rescaling and the sequence priority, for numpy arrays and torch tensors alike
# --------------------------------------------------------------------------------------------
def _xp(x):
    return torch if isinstance(x, torch.Tensor) else np


def value_rescale(x, eps: float = 1e-3):
    """h(x) = sign(x) (sqrt(|x| + 1) - 1) + eps x, elementwise; computed as
    ``x / (sqrt(|x| + 1) + 1) + eps x`` (the same value), which keeps small |x| exact."""
    xp = _xp(x)
    return x / (xp.sqrt(xp.abs(x) + 1) + 1) + eps * x


def inverse_value_rescale(x, eps: float = 1e-3):
    """h^-1(x) = sign(x) (u^2 - 1) with u = (sqrt(1 + 4 eps (|x| + 1 + eps)) - 1) / (2 eps), the
    paper's closed form (appendix A), computed as ``(u - 1)(u + 1)`` with ``u - 1`` rewritten
    without subtractions: the literal form loses most float32 digits for |x| < 1 (two
    cancellations), this one keeps ``h_inv(h(x)) == x`` to rounding over the whole range."""
    xp = _xp(x)
    ax = xp.abs(x)
    d = xp.sqrt(1 + 4 * eps * (ax + 1 + eps))
    u_minus_1 = 4 * ax * (ax + 1 + eps) / ((1 + 2 * ax + 2 * eps + d) * (d + 1))
    return xp.sign(x) * u_minus_1 * (u_minus_1 + 2)


def mixed_priority(abs_td, mask, eta: float = 0.9):
    """R2D2's sequence priority ``eta * max|delta| + (1 - eta) * mean|delta|`` over the steps
    where ``mask`` is true. abs_td float[..., T], mask bool[..., T] -> float[...]; 0 for a
    sequence without such steps."""
    xp = _xp(abs_td)
    z = abs_td * mask
    count = mask.sum(-1)
    count = count.clip(min=1)
    return eta * xp.amax(z, -1) + (1 - eta) * xp.sum(z, -1) / count
