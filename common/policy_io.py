"""Trained policies out of checkpoint files, for tools and for self-play opponents.

A checkpoint (``runs/<id>/checkpoints/ckpt-<updates>.pt``, written by the learner) is read as a
:class:`~zenrl.common.checkpoints.TrainingState`; this module needs its run configuration and
its policy network (the schema's ``network`` class, loaded with ``policy_state()``: the online
Q network of Ape-X, the actor-critic of A3C).

It lives in ``common/`` so that actors (which may not import ``learner/``) can load frozen
snapshots as opponents (:class:`SnapshotLeague`, :class:`SelfPlayWrapper`).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.checkpoints import TrainingState, list_checkpoints, read_checkpoint
from zenrl.common.config import RunConfig, SelfPlayConfig
from zenrl.common.errors import CheckpointError
from zenrl.common.networks import ActorCritic, flat_obs, num_actions, obs_spec, sample_categorical
from zenrl.common.recurrent import RecurrentQNetwork

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Reading checkpoints
# --------------------------------------------------------------------------------------------
def build_network(state: TrainingState, observation_space: gym.Space, action_space: gym.Space) -> torch.nn.Module:
    """The checkpoint's policy network (QNetwork for apex, ActorCritic for a3c), weights loaded,
    in eval mode on the CPU. ``observation_space`` / ``action_space`` are the single env's
    spaces; a mismatch with the trained network is a :class:`CheckpointError` naming the
    difference."""
    net = state.run_policy_network(obs_spec(observation_space), num_actions(action_space), state.run_config())
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
    if isinstance(obs, Mapping):
        return flat_obs({k: np.asarray(v)[None] for k, v in obs.items()})
    return flat_obs(np.asarray(obs)[None])


def greedy_actions(net: torch.nn.Module, flat: Mapping[str, np.ndarray]) -> np.ndarray:
    """int64[B]: argmax of the Q values (or of the policy logits for an actor-critic) for flat
    batched observations ``{"obs" | "obs/<key>": array[B, ...]}``."""
    with torch.no_grad():
        out = net({k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in flat.items()})
        if isinstance(out, tuple):
            out = out[0]
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

    def __call__(self, obs: Any) -> int:
        # a recurrent network's state follows every observation, whether its action is taken or not
        greedy = int(self.batch(single_to_flat(obs))[0]) if isinstance(self.net, RecurrentQNetwork) else None
        if self.epsilon > 0 and self.rng.random() < self.epsilon:
            return int(self.rng.integers(self.n_actions))
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
    return GreedyPolicy(net, num_actions(action_space), epsilon, seed, name=Path(path).name)


# --------------------------------------------------------------------------------------------
# Self-play: a league of frozen learner snapshots as match opponents
# --------------------------------------------------------------------------------------------
class SnapshotLeague:
    """Frozen copies of the learner, taken from its checkpoint directory at most every
    ``cfg.snapshot_interval_s`` (the newest checkpoint then, if not already held), at most
    ``cfg.max_snapshots`` kept (the oldest dropped first). One league per actor process; its
    envs share it. Never raises on a missing/vanishing checkpoint: it logs and keeps what it has.

    ``observation_space`` / ``action_space``: the single match env's spaces.
    """

    def __init__(self, cfg: SelfPlayConfig, checkpoint_dir: str | os.PathLike[str], observation_space: gym.Space,
                 action_space: gym.Space, seed: int = 0) -> None:
        self.cfg = cfg
        self.dir = Path(checkpoint_dir)
        self.observation_space, self.action_space = observation_space, action_space
        self.rng = np.random.default_rng(seed)
        self.snapshots: list[tuple[str, torch.nn.Module]] = []
        self._next_refresh = 0.0
        self._warned = False

    def refresh(self, now: float | None = None) -> bool:
        """Add the newest checkpoint if the interval has passed and it is new; True if added."""
        now = time.monotonic() if now is None else now
        if now < self._next_refresh:
            return False
        self._next_refresh = now + self.cfg.snapshot_interval_s
        files = list_checkpoints(self.dir)
        if not files:
            if not self._warned:
                log.info("self-play: no checkpoint in %s yet; scripted opponents only", self.dir)
                self._warned = True
            return False
        newest = files[-1]
        if any(name == newest.name for name, _ in self.snapshots):
            return False
        try:
            net = build_network(read_checkpoint(newest), self.observation_space, self.action_space)
        except CheckpointError as e:  # pruned between listing and reading, or half written
            log.warning("self-play: snapshot skipped: %s", e)
            return False
        self.snapshots.append((newest.name, net))
        del self.snapshots[:-self.cfg.max_snapshots]
        log.info("self-play: snapshot %s added (%d held)", newest.name, len(self.snapshots))
        return True

    def sample(self) -> tuple[str, torch.nn.Module] | None:
        """A uniformly drawn snapshot, or None while the league is empty."""
        if not self.snapshots:
            return None
        return self.snapshots[int(self.rng.integers(len(self.snapshots)))]


class SelfPlayWrapper(gym.Wrapper):
    """Per-episode opponent choice for a ``zenrl/BurgerWar*`` env: with probability
    ``cfg.snapshot_prob`` (once the league holds a snapshot) the episode is played against a
    snapshot drawn from ``league`` (the env's ``"policy"`` opponent), otherwise against the env's
    own draw from its scripted ``opponents``. Observations, rewards and the rest pass through.
    """

    def __init__(self, env: gym.Env, league: SnapshotLeague, seed: int = 0) -> None:
        super().__init__(env)
        self.league = league
        self.rng = np.random.default_rng(seed)
        self._policy = GreedyPolicy(torch.nn.Identity(), num_actions(env.action_space), league.cfg.epsilon,
                                    seed=seed + 1)
        # The env builds its "policy" opponent lazily from this attribute on the first episode
        # that names it (documented option ``opponent_policy``).
        env.unwrapped.opponent_policy = self._policy

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.league.refresh()
        options = dict(options or {})
        if "opponent" not in options and self.league.snapshots and self.rng.random() < self.league.cfg.snapshot_prob:
            name, net = self.league.sample()
            self._policy.net, self._policy.name = net, name
            self._policy.reset()
            options["opponent"] = "policy"
        return self.env.reset(seed=seed, options=options)


def wrap_selfplay(envs: list[gym.Env], cfg: RunConfig, run_id: str, seed: int) -> list[gym.Env]:
    """Wrap an actor's envs for self-play (``cfg.selfplay``), all sharing one
    :class:`SnapshotLeague` on ``cfg.selfplay.checkpoint_dir`` (default
    ``<runs_dir>/<run_id>/checkpoints``, the learner's, on a shared filesystem)."""
    sp = cfg.selfplay
    ckpt_dir = Path(sp.checkpoint_dir) if sp.checkpoint_dir else Path(cfg.runs_dir) / run_id / "checkpoints"
    league = SnapshotLeague(sp, ckpt_dir, envs[0].observation_space, envs[0].action_space, seed)
    return [SelfPlayWrapper(e, league, seed + 7919 * (i + 1)) for i, e in enumerate(envs)]
