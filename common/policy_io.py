"""Trained policies out of checkpoint and exported files, for tools and for match opponents.

A checkpoint (``runs/<id>/checkpoints/ckpt-<updates>.pt``, written by the learner) is read as a
:class:`~zenrl.common.checkpoints.TrainingState`; this module needs its run configuration and
its policy network (the schema's ``network`` class, loaded with ``policy_state()``: the online
Q network of Ape-X, the actor-critic of A3C).

An exported file (``zenrl export``: TorchScript plus a ``zenrl.json`` description) is a program,
loaded only where the user said so (:class:`ExportedPlayer`).

It lives in ``common/`` so that actors (which may not import ``learner/`` or ``zenrl/``) can load
frozen policies as match opponents (:mod:`zenrl.common.opponents`).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import warnings
import zipfile
from pathlib import Path
from typing import Any, Mapping

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.checkpoints import TrainingState, read_checkpoint
from zenrl.common.errors import CheckpointError, ZenrlError
from zenrl.common.networks import ActorCritic, action_size, flat_obs, obs_spec, sample_categorical
from zenrl.common.recurrent import RecurrentQNetwork
from zenrl.common.specs import SEP, flatten

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Reading checkpoints
# --------------------------------------------------------------------------------------------
def build_network(state: TrainingState, observation_space: gym.Space, action_space: gym.Space) -> torch.nn.Module:
    """The checkpoint's policy network (QNetwork for apex, ActorCritic for a3c), weights loaded,
    in eval mode on the CPU. ``observation_space`` / ``action_space`` are the single env's
    spaces; a mismatch with the trained network is a :class:`CheckpointError` naming the
    difference."""
    try:
        n = action_size(action_space, state.algo)
    except ValueError as e:
        raise CheckpointError(f"the checkpoint's policy cannot act in this env: {e}") from None
    net = state.run_policy_network(obs_spec(observation_space), n, state.run_config())
    try:
        net.load_state_dict(state.policy_state())
    except RuntimeError as e:
        raise CheckpointError(f"the checkpoint's network does not fit this env's spaces "
                              f"(obs {observation_space}, actions {action_space}): {e}") from None
    return net.eval()


# --------------------------------------------------------------------------------------------
# Greedy policy on single observations
# --------------------------------------------------------------------------------------------
def single_to_flat(obs: Any) -> dict[str, np.ndarray]:
    """One observation (array or dict of arrays, no batch dim) -> flat arrays with B = 1."""
    return flat_obs(_batch_of_one(obs))


def _batch_of_one(obs: Any) -> Any:
    if isinstance(obs, Mapping):
        return {k: _batch_of_one(v) for k, v in obs.items()}
    return np.asarray(obs)[None]


def greedy_actions(net: torch.nn.Module, flat: Mapping[str, np.ndarray]) -> np.ndarray:
    """int64[B]: argmax of the Q values (or of the policy logits for an actor-critic) for flat
    batched observations ``{"obs" | "obs/<key>": array[B, ...]}``; a Gaussian actor-critic's
    mean actions float32[B, d] (continuous actions)."""
    with torch.no_grad():
        out = net({k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in flat.items()})
        if isinstance(out, tuple):
            out = out[0]
        if getattr(net, "continuous", False):
            return out.float().numpy()
        return out.argmax(1).numpy()


def recurrent_greedy_actions(net: RecurrentQNetwork, flat: Mapping[str, np.ndarray],
                             state: tuple[torch.Tensor, torch.Tensor] | None) -> tuple[np.ndarray, tuple[torch.Tensor, torch.Tensor]]:
    """int64[B] argmax actions of a recurrent Q network for flat batched observations, one step
    from ``state`` ((h, c) float32[B, H] each; None: zero, an episode's start), and the state after."""
    with torch.no_grad():
        obs = {k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in flat.items()}
        if state is None:
            state = net.initial_state(len(next(iter(flat.values()))))
        q, state = net.step(obs, state)
    return q.argmax(1).numpy(), state


def sampled_actions(net: torch.nn.Module, flat: Mapping[str, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """int64[B]: actions drawn from an actor-critic's categorical policy (softmax of its logits)
    with ``rng``, for flat batched observations. A Q network has no policy to sample from:
    :class:`ValueError`."""
    if not isinstance(net, ActorCritic):
        raise ValueError("sampling actions needs an actor-critic (a3c) network; a Q network is greedy only")
    with torch.no_grad():
        logits = net({k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in flat.items()})[0]
        if net.continuous:  # float32[B, d]: mean + std * N(0, 1)
            std = net.clamped_log_std().exp().double().numpy()
            mean = logits.double().numpy()
            return (mean + std * rng.standard_normal(mean.shape)).astype(np.float32)
    return sample_categorical(logits.double().numpy(), rng)


class GreedyPolicy:
    """``policy(obs) -> int`` on single observations (what the match env's ``opponent_policy``
    and the tools call), with optional epsilon-random actions from its own generator.

    ``net``: a QNetwork / ActorCritic; ``n_actions``: size of the discrete action space;
    ``sample``: draw actions from an actor-critic's policy instead of taking its argmax (the
    policy A3C trains; a :class:`ValueError` for a Q network). :meth:`reseed` makes a sampled
    episode reproducible. A recurrent Q network (R2D2) carries its state from call to call:
    :meth:`reset` where an episode begins.
    """

    def __init__(self, net: torch.nn.Module, n_actions: int, epsilon: float = 0.0, seed: int | None = None,
                 name: str = "policy", sample: bool = False) -> None:
        if sample and not isinstance(net, ActorCritic):
            raise ValueError("sampling actions needs an actor-critic (a3c) checkpoint; a Q network is greedy only")
        self.net = net
        self.n_actions = int(n_actions)
        self.epsilon = float(epsilon)
        self.sample = bool(sample)
        self.rng = np.random.default_rng(seed)
        self.name = name
        self._state: tuple[torch.Tensor, torch.Tensor] | None = None  # a recurrent network's, since reset()

    def reseed(self, seed: int | None) -> None:
        """Restart the policy's own random stream (epsilon and sampling) from ``seed``."""
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        """An episode begins: a recurrent network's state goes back to zero (a feed-forward
        network has none)."""
        self._state = None

    def __call__(self, obs: Any) -> int | np.ndarray:
        # a recurrent network's state follows every observation, whether its action is taken or not
        greedy = int(self.batch(single_to_flat(obs))[0]) if isinstance(self.net, RecurrentQNetwork) else None
        continuous = getattr(self.net, "continuous", False)
        if self.epsilon > 0 and self.rng.random() < self.epsilon:
            if continuous:  # a uniform point of [-1, 1]^d
                return self.rng.uniform(-1.0, 1.0, self.n_actions).astype(np.float32)
            return int(self.rng.integers(self.n_actions))
        if continuous:
            return self.batch(single_to_flat(obs))[0]
        return greedy if greedy is not None else int(self.batch(single_to_flat(obs))[0])

    def batch(self, flat: Mapping[str, np.ndarray]) -> np.ndarray:
        """int64[B] actions (greedy, or sampled) for flat batched observations (no epsilon)."""
        if self.sample:
            return sampled_actions(self.net, flat, self.rng)
        if isinstance(self.net, RecurrentQNetwork):
            if self._state is not None and self._state[0].shape[0] != len(next(iter(flat.values()))):
                self._state = None  # another batch: other episodes
            actions, self._state = recurrent_greedy_actions(self.net, flat, self._state)
            return actions
        return greedy_actions(self.net, flat)


def load_policy(path: str | os.PathLike[str], observation_space: gym.Space, action_space: gym.Space,
                epsilon: float = 0.0, seed: int | None = None) -> GreedyPolicy:
    """Checkpoint file -> :class:`GreedyPolicy` for an env with these (single) spaces."""
    state = read_checkpoint(path)
    net = build_network(state, observation_space, action_space)
    return GreedyPolicy(net, action_size(action_space, state.algo), epsilon, seed, name=Path(path).name)


# --------------------------------------------------------------------------------------------
# Exported (TorchScript) policies
# --------------------------------------------------------------------------------------------
def is_exported(path: str | os.PathLike[str]) -> bool:
    """True for a file written by ``zenrl export`` (a TorchScript archive carrying
    ``extra/zenrl.json``), False for anything else (a checkpoint, a missing file)."""
    try:
        with zipfile.ZipFile(path) as z:
            return any(n.endswith("/extra/zenrl.json") for n in z.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


class ExportedPlayer:
    """``player(obs) -> int`` for one observation, from a ``zenrl export`` file: the greedy policy
    as TorchScript plus its ``zenrl.json`` description (env id and kwargs, input shapes and dtypes,
    number of actions). ``meta`` is that description. A continuous policy's program returns the
    action in the env's units (``action_bounds``); the player gives it in the [-1, 1] units of
    zenrl's envs (float32[d]). A discrete program returns the env's action (``action_start`` + the
    index, for a ``Discrete(n, start)`` env); the player gives the index, as zenrl's envs take it.

    A TorchScript file is a program (its graph runs when called): load only files you trust, such
    as the ones in ``models/``. Checkpoints (``torch.load(weights_only=True)``) carry weights only.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        extra = {"zenrl.json": ""}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                self.module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
            self.meta = json.loads(extra["zenrl.json"])
        except Exception as e:  # torch raises many types for a damaged archive
            raise ZenrlError(f"exported policy {str(path)!r} is unreadable: {type(e).__name__}: {e}") from None
        if not isinstance(self.meta, dict) or not isinstance(self.meta.get("inputs"), dict) or "env" not in self.meta:
            raise ZenrlError(f"exported policy {str(path)!r}: zenrl.json lacks 'env' or 'inputs'")
        self.module.eval()
        self.name = Path(path).name
        self.n_actions = int(self.meta.get("n_actions", 0))
        #: continuous actions: the env's (low, high) the program's output lies within; None: an index
        b = self.meta.get("action_bounds")
        self.bounds = (np.asarray(b["low"], np.float64), np.asarray(b["high"], np.float64)) if isinstance(b, dict) else None
        #: a Discrete(n, start) env's start: the program returns start + index
        self.start = int(self.meta.get("action_start", 0))
        self.keys = list(self.meta["inputs"])
        self.dict_obs = self.keys != ["obs"]
        self.nested = any(SEP in k for k in self.keys)
        #: a mixed policy's member count (``zenrl export --member``); 1 for one network
        self.members = int(self.meta.get("members", 1))
        if self.members > 1 and not hasattr(self.module, "pick"):
            raise ZenrlError(f"exported policy {str(path)!r}: zenrl.json names {self.members} members, the program has no pick()")
        self.rng = np.random.default_rng()
        #: the member this player's match is played by (seated in the program before each call)
        self.current = 0

    def for_env(self) -> "ExportedPlayer":
        """A player for one env of several sharing this file's program: itself for one network;
        for a mixed policy a copy (the same program) with its own member and draw, so that each
        env's match keeps its member while the others' matches begin and end."""
        if self.members == 1:
            return self
        seat = copy.copy(self)
        seat.rng, seat.current = np.random.default_rng(), 0
        return seat

    def check_spaces(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        """:class:`ZenrlError` naming the first input or the action count that differs from the env's.
        The env may give more observation keys than the policy reads (e.g. ``enemy_seen`` to a
        policy trained without it): it reads its own keys only."""
        spaces = flatten(observation_space.spaces) if isinstance(observation_space, gym.spaces.Dict) else {"obs": observation_space}
        if not set(self.keys) <= set(spaces):
            raise ZenrlError(f"{self.name}: exported for observation keys {sorted(self.keys)}, the env has {sorted(spaces)}")
        for k, want in self.meta["inputs"].items():
            sp = spaces[k]
            if list(sp.shape) != list(want.get("shape", [])) or str(sp.dtype) != want.get("dtype"):
                raise ZenrlError(f"{self.name}: input {k!r} exported as {want.get('dtype')}{want.get('shape')}, "
                                 f"the env gives {sp.dtype}{list(sp.shape)}")
        if self.bounds is not None:  # zenrl's envs present a continuous action space as [-1, 1]^d
            if not isinstance(action_space, gym.spaces.Box) or action_space.shape != (self.n_actions,):
                raise ZenrlError(f"{self.name}: exported for continuous actions of {self.n_actions} dimensions, "
                                 f"the env has {action_space}")
            return
        n = getattr(action_space, "n", None)
        if n is None or int(n) != self.n_actions:
            raise ZenrlError(f"{self.name}: exported for {self.n_actions} actions, the env has {action_space}")

    def reseed(self, seed: int | None) -> None:
        """Restart the draw of a mixed policy's members from ``seed`` (one network: greedy,
        nothing to draw)."""
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        """A match begins: a mixed policy seats a member drawn uniformly (one network: no state
        between observations, nothing to do)."""
        if self.members > 1:
            self.current = int(self.rng.integers(self.members))

    def __call__(self, obs: Any) -> int | np.ndarray:
        if self.members > 1:
            self.module.pick(self.current)
        with torch.no_grad():
            if self.dict_obs:  # a Dict inside a Dict: the program's keys are paths ("a/b")
                flat = flatten(obs) if self.nested else obs
                x = {k: torch.as_tensor(np.ascontiguousarray(flat[k])) for k in self.keys}
            else:
                x = torch.as_tensor(np.ascontiguousarray(obs))
            out = self.module(x)
        if self.bounds is not None:  # the env's units back to the [-1, 1] zenrl's envs take
            low, high = self.bounds
            return (2.0 * (out.double().numpy() - low) / (high - low) - 1.0).astype(np.float32)
        return int(out) - self.start


def initial_q_weights(path: str | os.PathLike[str], exported: bool) -> dict[str, torch.Tensor]:
    """The Q-network weights (``state_dict``) a fresh Ape-X/R2D2 learner starts from
    (``learner.init_from``): the online network of a checkpoint, read weights-only, or, with
    ``exported``, the network inside a ``zenrl export`` file (whose scripted module holds it as
    ``net``). A :class:`ZenrlError` names the file and what is wrong with it."""
    if exported:
        if not is_exported(path):
            raise ZenrlError(f"learner.init_from {str(path)!r} is not a `zenrl export` file (learner.init_exported is set)")
        player = ExportedPlayer(path)
        if player.members > 1:
            raise ZenrlError(f"learner.init_from {str(path)!r} is a mixed policy of {player.members} networks; "
                             "a learner starts from one (name one of its checkpoints)")
        module = player.module
        sd = {k[len("net."):]: v.detach().clone() for k, v in module.state_dict().items() if k.startswith("net.")}
        if not sd:
            raise ZenrlError(f"learner.init_from {str(path)!r}: the exported file holds no Q-network weights")
        return sd
    if is_exported(path):
        raise ZenrlError(f"learner.init_from {str(path)!r} is a `zenrl export` file: set learner.init_exported "
                         "to load it (it is a program)")
    try:
        state = read_checkpoint(path)
    except CheckpointError as e:
        raise ZenrlError(f"learner.init_from: {e}") from None
    online = state.learner.get("online") if isinstance(getattr(state, "learner", None), Mapping) else None
    if not isinstance(online, Mapping):
        raise ZenrlError(f"learner.init_from {str(path)!r} is not an Ape-X or R2D2 checkpoint (no Q-network in it)")
    return dict(online)
