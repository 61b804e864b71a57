"""Networks shared by actors and learners: encoders per observation kind, a dueling Q head, an
actor-critic head, and the helpers that turn Gymnasium spaces into flat array specs.

Observations reach a network as a flat mapping of tensors named as in the replay: ``"obs"`` for
a plain ``Box`` space, ``"obs/<key>"`` for each key of a ``Dict`` space. Shapes::

    Box float (D...)            -> "obs":        float32[B, D...]   (flattened, MLP)
    Box uint8 (H, W, C)         -> "obs":        uint8[B, H, W, C]  (Nature conv, /255 on device)
    Box uint8 (k, H, W), k <= 4 -> "obs":        uint8[B, k, H, W]  (frame stacks, channels first)
    Dict {k: Box}               -> "obs/k":      one encoder per key, outputs concatenated
"""

from __future__ import annotations

import hashlib
import math
from typing import Mapping

import gymnasium as gym
import numpy as np
import torch
from threadpoolctl import threadpool_limits
from torch import nn
from torch.nn import functional as F

from zenrl.common.config import NetworkConfig
from zenrl.common.errors import ConfigError
from zenrl.common.specs import ArraySpec, obs_fields


# --------------------------------------------------------------------------------------------
# Spaces -> specs
# --------------------------------------------------------------------------------------------
def obs_spec(space: gym.Space, prefix: str = "obs") -> dict[str, ArraySpec]:
    """Flat spec of one observation: ``{"obs": ...}`` or ``{"obs/<key>": ...}`` (see
    :func:`zenrl.common.specs.obs_fields`)."""
    return {k: f.spec for k, f in obs_fields(space, prefix).items()}


def flat_obs(obs, prefix: str = "obs") -> dict[str, np.ndarray]:
    """Batched observation (array or dict of arrays, leading dim B) -> flat named arrays."""
    if isinstance(obs, Mapping):
        out: dict[str, np.ndarray] = {}
        for k, v in obs.items():
            out.update(flat_obs(v, f"{prefix}/{k}"))
        return out
    a = np.asarray(obs)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    return {prefix: a}


def rename_prefix(flat: Mapping[str, np.ndarray], old: str, new: str) -> dict[str, np.ndarray]:
    """``{"next_obs/x": a}`` -> ``{"obs/x": a}`` (fields with other prefixes are dropped)."""
    out = {}
    for k, v in flat.items():
        if k == old:
            out[new] = v
        elif k.startswith(old + "/"):
            out[new + k[len(old):]] = v
    return out


class BoxActions(int):
    """The size d of a continuous action (a 1-D ``Box`` of d dimensions) as the policy head's
    size, marked as such: an :class:`ActorCritic` built with it has a Gaussian policy over
    actions normalised to [-1, 1]^d (:func:`zenrl.common.env_factory.make_env` rescales and
    clips them to the env's bounds)."""

    def __repr__(self) -> str:
        return f"BoxActions({int(self)})"


#: Largest continuous action accepted (dimensions of a Box action space).
MAX_BOX_ACTION_DIMS = 256


def num_actions(space: gym.Space, algo: str | None = None) -> int:
    """The number of actions of a ``Discrete`` space (what a Q network or a categorical policy
    needs); any other space is a :class:`ValueError` naming ``algo`` (the algorithm asking)."""
    if not isinstance(space, gym.spaces.Discrete):
        who = f"algo: {algo}" if algo else "this algorithm"
        hint = "; algo: impala (IMPALA / APPO) and a3c take continuous (Box) actions" if isinstance(space, gym.spaces.Box) else ""
        raise ValueError(f"{who} needs a Discrete action space, got {space}{hint}")
    return int(space.n)


def policy_actions(space: gym.Space) -> int:
    """The size of an actor-critic's policy head for ``space``: ``n`` for ``Discrete(n)`` (a
    categorical policy), :class:`BoxActions` ``(d)`` for a 1-D ``Box`` of d dimensions with finite
    bounds (a Gaussian policy). :class:`ValueError` naming the space otherwise."""
    if isinstance(space, gym.spaces.Box):
        if len(space.shape) != 1 or not 1 <= space.shape[0] <= MAX_BOX_ACTION_DIMS:
            raise ValueError(f"continuous actions must be a 1-D Box of 1..{MAX_BOX_ACTION_DIMS} dimensions, got {space}")
        if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()):
            raise ValueError(f"continuous actions need finite bounds (they are rescaled to [-1, 1]), got {space}")
        return BoxActions(space.shape[0])
    return num_actions(space)


#: The algorithms whose actor-critic takes continuous (Box) actions.
CONTINUOUS_ALGOS = frozenset({"impala", "a3c"})


def action_size(space: gym.Space, algo: str) -> int:
    """The size of ``algo``'s policy (or Q) head for ``space``: :func:`policy_actions` for the
    algorithms that take continuous actions, :func:`num_actions` (Discrete only) for the others."""
    return policy_actions(space) if algo in CONTINUOUS_ALGOS else num_actions(space, algo)


def is_continuous(n_actions: int) -> bool:
    """Whether a policy head of this size is a Gaussian one (:class:`BoxActions`)."""
    return isinstance(n_actions, BoxActions)


#: Bounds of a Gaussian policy's log standard deviation (in normalised action units), applied
#: where it is used: below, the policy could grow arbitrarily sure (and its log-densities
#: arbitrarily large); above, its samples would almost all be clipped to the bounds.
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def policy_logp_entropy(logits: torch.Tensor, action: torch.Tensor,
                        log_std: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """log pi(a|x) and the policy's entropy H(pi(.|x)), both float[...] over the samples' leading
    dimensions ([T, B] below; [N] works alike).

    Categorical (``log_std`` None): ``logits`` float[T, B, A], ``action`` int64[T, B].
    Gaussian (continuous actions): ``logits`` the means float[T, B, d], ``action`` float[T, B, d],
    ``log_std`` float[d] (clamped); independent normals, so both are sums over the d dimensions:
    ``log pi = sum(-(a - mu)^2 / (2 sigma^2) - log sigma - log(2 pi) / 2)``,
    ``H = sum(log sigma + (1 + log(2 pi)) / 2)``."""
    if log_std is None:
        logp_all = F.log_softmax(logits, dim=-1)
        logp = logp_all.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
        return logp, -(logp_all.exp() * logp_all).sum(-1)
    z = (action.to(logits.dtype) - logits) * torch.exp(-log_std)
    logp = (-0.5 * z * z - log_std - _HALF_LOG_2PI).sum(-1)
    entropy = (log_std + 0.5 + _HALF_LOG_2PI).sum().expand_as(logp)
    return logp, entropy


def gaussian_logp(mean: np.ndarray, log_std: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """float64[B]: log-density of ``actions`` [B, d] under independent normals ``mean`` [B, d],
    ``log_std`` [d] (already clamped), summed over the d dimensions."""
    z = (actions - mean) / np.exp(log_std)
    return (-0.5 * z * z - log_std - _HALF_LOG_2PI).sum(axis=1)


# --------------------------------------------------------------------------------------------
# Encoders
# --------------------------------------------------------------------------------------------
class MLPEncoder(nn.Module):
    """float[B, *shape] -> float[B, prod(shape)] (flatten only; the trunk adds layers)."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        self.out_dim = int(np.prod(shape)) if shape else 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(x.shape[0], -1).float()


class OneHotEncoder(nn.Module):
    """int64[B] category indices of a ``Discrete(n, start)`` observation -> float[B, n] one-hot
    (as SB3 and RLlib feed such observations: an index is a name, not a quantity). Indices
    outside the space are clamped into it (the replay and learners refuse them before)."""

    def __init__(self, start: int, n: int) -> None:
        super().__init__()
        self.start, self.out_dim = int(start), int(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        i = (x.reshape(x.shape[0]).long() - self.start).clamp(0, self.out_dim - 1)
        return nn.functional.one_hot(i, self.out_dim).float()


class ConvEncoder(nn.Module):
    """Nature-DQN conv torso. uint8[B, H, W, C] -> float[B, F]; scaled by 1/255 on the device.
    A shape ``(k, H, W)`` with ``k <= 4 < W`` is a stack of k frames on the first axis
    (gymnasium's FrameStackObservation, and how the replay stores stacks): channels first."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        self.channels_first = shape[0] <= 4 < shape[2]
        c, h, w = shape if self.channels_first else (shape[2], shape[0], shape[1])
        if min(h, w) >= 36:
            layers = [nn.Conv2d(c, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(), nn.Conv2d(64, 64, 3, 1), nn.ReLU()]
        else:  # small images (e.g. 32x32): a lighter stack that still fits
            layers = [nn.Conv2d(c, 32, 3, 2), nn.ReLU(), nn.Conv2d(32, 64, 3, 2), nn.ReLU()]
        self.net = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            self.out_dim = int(self.net(torch.zeros(1, c, h, w)).shape[1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.channels_first:
            x = x.permute(0, 3, 1, 2)
        return self.net(x.float() * (1.0 / 255.0))


class ObsEncoder(nn.Module):
    """One encoder per observation field, outputs concatenated: ``{name: tensor[B, ...]}`` ->
    float[B, F]."""

    def __init__(self, spec: Mapping[str, ArraySpec], conv: bool = True) -> None:
        super().__init__()
        self.names = sorted(spec)
        encs = {}
        for name in self.names:
            s = spec[name]
            if s.categories is not None:
                encs[name.replace("/", "__")] = OneHotEncoder(*s.categories)
            elif conv and s.dtype == "uint8" and len(s.shape) == 3:
                encs[name.replace("/", "__")] = ConvEncoder(s.shape)
            else:
                encs[name.replace("/", "__")] = MLPEncoder(s.shape)
        self.encoders = nn.ModuleDict(encs)
        self._keys = [n.replace("/", "__") for n in self.names]
        self.out_dim = sum(e.out_dim for e in self.encoders.values())

    def fields(self) -> list[tuple[str, nn.Module]]:
        """``(field name, its encoder)`` in the order their outputs are concatenated."""
        return [(n, self.encoders[k]) for n, k in zip(self.names, self._keys)]

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        if len(self.names) == 1:
            return self.encoders[self._keys[0]](obs[self.names[0]])
        return torch.cat([self.encoders[k](obs[n]) for k, n in zip(self._keys, self.names)], dim=1)


_ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh}


def mlp(in_dim: int, hidden: list[int], activation: str = "relu") -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), _ACTIVATIONS[activation]()]
        d = h
    return nn.Sequential(*layers), d


class QNetwork(nn.Module):
    """Q(s, .): ``{name: tensor[B, ...]}`` -> float32[B, A]. Dueling:
    ``Q = V + A - mean(A)``."""

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, cfg: NetworkConfig) -> None:
        super().__init__()
        self.encoder = ObsEncoder(spec, cfg.conv)
        self.trunk, d = mlp(self.encoder.out_dim, list(cfg.hidden), cfg.activation)
        self.dueling = cfg.dueling
        if cfg.dueling:
            self.value = nn.Linear(d, 1)
            self.advantage = nn.Linear(d, n_actions)
        else:
            self.q = nn.Linear(d, n_actions)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        h = self.trunk(self.encoder(obs))
        if self.dueling:
            a = self.advantage(h)
            return self.value(h) + a - a.mean(dim=1, keepdim=True)
        return self.q(h)


def sample_categorical(logits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Draw a ~ softmax(logits) per row (Gumbel-max). logits float[B, A] -> int64[B]."""
    g = -np.log(-np.log(rng.random(logits.shape)))
    return (logits + g).argmax(1).astype(np.int64)


def set_compute_threads(n: int) -> None:
    """Use ``n`` threads for torch's intra-op work and for numpy's BLAS (the numpy forward of
    :class:`NumpyQ`). OpenBLAS otherwise starts one thread per CPU: on a 2-core machine shared
    with the replay, a [128, 128] forward on 64 observations took 48 us instead of 38 us, and
    the actor made 108 k env steps/s instead of ~120 k."""
    torch.set_num_threads(n)
    threadpool_limits(limits=n, user_api="blas")


class NumpyInputs:
    """What an MLP-only :class:`ObsEncoder` gives, in numpy, for the actors' numpy forwards:
    flat observations ``{name: array[B, ...]}`` -> float32[B, F], each field flattened, or one-hot
    encoded as :class:`OneHotEncoder` does, concatenated in the encoder's order."""

    def __init__(self, encoder: ObsEncoder) -> None:
        #: (field, (start, n) of a one-hot encoded field or None), in the encoder's order
        self.fields = [(n, (e.start, e.out_dim) if isinstance(e, OneHotEncoder) else None) for n, e in encoder.fields()]

    @staticmethod
    def supports(encoder: ObsEncoder) -> bool:
        """Whether every field is flattened or one-hot encoded (no conv encoder)."""
        return all(isinstance(e, (MLPEncoder, OneHotEncoder)) for e in encoder.encoders.values())

    def __call__(self, flat: Mapping[str, np.ndarray]) -> np.ndarray:
        parts = [np.asarray(flat[n], np.float32).reshape(len(flat[n]), -1) if oh is None else _one_hot(flat[n], *oh)
                 for n, oh in self.fields]
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)


def _one_hot(x: np.ndarray, start: int, n: int) -> np.ndarray:
    """int[B] indices -> float32[B, n], as :class:`OneHotEncoder`."""
    i = np.clip(np.asarray(x, np.int64).reshape(-1) - start, 0, n - 1)
    out = np.zeros((i.shape[0], n), np.float32)
    out[np.arange(i.shape[0]), i] = 1.0
    return out


class NumpyQ:
    """A numpy copy of an MLP-only :class:`QNetwork` (its Q values) or :class:`ActorCritic` (its
    policy logits; the value MLP is left out) for acting on the CPU: flat observations
    ``{name: array[B, ...]}`` -> float32[B, A], the same values as the network's forward (to
    float32 rounding). For the small MLPs actors run, torch's per-op dispatch costs more than
    the arithmetic (measured: 0.21 ms vs 0.07 ms for a [64, 64] dueling net on 64
    observations). :meth:`of` gives None for networks with conv encoders; call :meth:`load`
    after the network's weights change.

    The dueling head is linear in the last hidden layer ``h``, so :meth:`load` folds it into
    one layer: ``V + A - mean(A) = h @ (w_v + W_a - mean_a W_a) + (b_v + b_a - mean(b_a))``
    (computed in float64, stored as float32): one matmul instead of two plus a mean (a [128,
    128] net on 64 observations: 38 -> 31 us)."""

    def __init__(self, net: "QNetwork | ActorCritic") -> None:
        self.inputs = NumpyInputs(net.encoder)
        self.act = np.tanh if isinstance(net.trunk[1], nn.Tanh) else None
        self.dueling = isinstance(net, QNetwork) and net.dueling
        #: a Gaussian actor-critic's mean is the tanh of its policy head
        self.squash = isinstance(net, ActorCritic) and net.continuous
        self.load(net)

    @staticmethod
    def of(net: nn.Module) -> "NumpyQ | None":
        if not isinstance(net, (QNetwork, ActorCritic)) or not NumpyInputs.supports(net.encoder):
            return None
        return NumpyQ(net)

    def load(self, net: "QNetwork | ActorCritic") -> None:
        def wb(layer: nn.Linear) -> tuple[np.ndarray, np.ndarray]:
            return (np.ascontiguousarray(layer.weight.detach().cpu().numpy().T, np.float32),
                    layer.bias.detach().cpu().numpy().astype(np.float32))

        self.layers = [wb(m) for m in net.trunk if isinstance(m, nn.Linear)]
        if not self.dueling:
            self.head = wb(net.policy if isinstance(net, ActorCritic) else net.q)
            return
        (wv, bv), (wa, ba) = (tuple(x.astype(np.float64) for x in wb(m)) for m in (net.value, net.advantage))
        w = wv + wa - wa.mean(axis=1, keepdims=True)  # [d, 1] broadcast over the A columns
        b = bv + ba - ba.mean()
        self.head = (np.ascontiguousarray(w, np.float32), b.astype(np.float32))

    def __call__(self, flat: Mapping[str, np.ndarray]) -> np.ndarray:
        h = self.inputs(flat)
        for w, b in self.layers:
            h = h @ w
            h += b
            if self.act is None:
                np.maximum(h, 0.0, out=h)
            else:
                self.act(h, out=h)
        w, b = self.head
        q = h @ w
        q += b
        if self.squash:
            np.tanh(q, out=q)
        return q




class ActorCritic(nn.Module):
    """Policy and value: ``{name: tensor[B, ...]}`` -> (logits float32[B, A], value float32[B]).
    With ``cfg.shared_torso`` false the value head has its own MLP (``value_trunk``) on the shared
    encoder.

    ``n_actions`` a :class:`BoxActions` ``(d)``: a Gaussian policy over actions normalised to
    [-1, 1]^d; the first output is then the mean float32[B, d] (``tanh`` of the policy head: a
    mean outside [-1, 1] would act as its bound, with no gradient to bring it back), and ``log_std`` float32[d] a
    parameter of its own (state-independent, as in PPO's continuous-control setting), used
    clamped to [LOG_STD_MIN, LOG_STD_MAX] (:meth:`clamped_log_std`); ``continuous`` says which."""

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, cfg: NetworkConfig) -> None:
        super().__init__()
        self.encoder = ObsEncoder(spec, cfg.conv)
        self.trunk, d = mlp(self.encoder.out_dim, list(cfg.hidden), cfg.activation)
        self.value_trunk = None if cfg.shared_torso else mlp(self.encoder.out_dim, list(cfg.hidden), cfg.activation)[0]
        self.continuous = is_continuous(n_actions)
        self.policy = nn.Linear(d, int(n_actions))
        self.value = nn.Linear(d, 1)
        if self.continuous:
            self.log_std = nn.Parameter(torch.full((int(n_actions),), float(cfg.log_std_init)))
        if cfg.orthogonal_init:
            self._orthogonal_init()

    def clamped_log_std(self) -> torch.Tensor:
        """float32[d]: the Gaussian policy's log standard deviation as used (continuous only)."""
        return self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def _orthogonal_init(self) -> None:
        """Orthogonal weights, zero biases: gain sqrt(2) in the MLPs (conv layers keep their
        init), 0.01 for the policy head (near-uniform first policy), 1 for the value head."""
        trunks = [self.trunk] + ([self.value_trunk] if self.value_trunk is not None else [])
        for layer in (m for t in trunks for m in t.modules() if isinstance(m, nn.Linear)):
            nn.init.orthogonal_(layer.weight, gain=math.sqrt(2))
            nn.init.zeros_(layer.bias)
        for head, gain in ((self.policy, 0.01), (self.value, 1.0)):
            nn.init.orthogonal_(head.weight, gain=gain)
            nn.init.zeros_(head.bias)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.encoder(obs)
        h = self.trunk(z)
        hv = h if self.value_trunk is None else self.value_trunk(z)
        out = self.policy(h)
        if self.continuous:  # the mean stays inside the action range the env clips to
            out = torch.tanh(out)
        return out, self.value(hv).squeeze(1)


# --------------------------------------------------------------------------------------------
# Parameters <-> arrays
# --------------------------------------------------------------------------------------------
def arch_fingerprint(net: nn.Module) -> str:
    """A short string that differs when any parameter's name or shape differs."""
    desc = ";".join(f"{k}:{tuple(v.shape)}" for k, v in net.state_dict().items())
    return f"{type(net).__name__}-{hashlib.sha1(desc.encode()).hexdigest()[:12]}"


def params_to_arrays(net: nn.Module) -> dict[str, np.ndarray]:
    """state_dict -> ``{name: np.ndarray}`` on the CPU (copies)."""
    return {k: v.detach().to("cpu").numpy().copy() for k, v in net.state_dict().items()}


def arrays_to_params(net: nn.Module, arrays: Mapping[str, np.ndarray]) -> None:
    """Load ``{name: array}`` into ``net``; raises ValueError naming a missing/mismatched one."""
    sd = net.state_dict()
    if set(arrays) != set(sd):
        missing = sorted(set(sd) - set(arrays))
        extra = sorted(set(arrays) - set(sd))
        raise ValueError(f"parameter names differ: missing {missing[:3]}, unexpected {extra[:3]}")
    new = {}
    for k, t in sd.items():
        a = arrays[k]
        if tuple(a.shape) != tuple(t.shape):
            raise ValueError(f"parameter {k} has shape {tuple(a.shape)}, expected {tuple(t.shape)}")
        new[k] = torch.from_numpy(np.array(a, dtype=np.float32 if a.dtype.kind == "f" else a.dtype, copy=True))
    net.load_state_dict(new)


def to_tensors(flat: Mapping[str, np.ndarray], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Numpy arrays (possibly read-only views) -> tensors on ``device``."""
    out = {}
    for k, v in flat.items():
        a = v if v.flags.writeable else np.array(v)
        out[k] = torch.from_numpy(a).to(device, non_blocking=True)
    return out


def resolve_device(name: str, option: str = "learner.device") -> torch.device:
    """``auto``: CUDA where torch sees a GPU, else the CPU. Any other ``name`` must be a device
    this torch has here: :class:`~zenrl.common.errors.ConfigError` naming ``option`` otherwise (a
    learner exits at once with it; before, it failed in torch's first call and was restarted)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise ConfigError(f"{option} = {name!r} is not a torch device: auto, cpu, cuda, cuda:N or mps") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"{option} = {name!r}, but this torch sees no CUDA device (a CPU build of torch, or no "
                              f"GPU driver): use {option}=auto or cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"{option} = {name!r}, but this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"{option} = {name!r}, but this torch has no MPS device: use {option}=auto or cpu")
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{option} = {name!r}: zenrl trains on cpu, cuda or mps")
    return dev
