"""Match opponents for training: a pool of named opponents (scripted bots and frozen policies),
one drawn per episode by a pluggable chooser, each finished match reported to a callback.

* :class:`Opponent` / :class:`OpponentPool`: named opponents, each a scripted ``bot`` of the
  match env, a frozen checkpoint's network (``"checkpoint"``, read weights only), a ``zenrl
  export`` file (``"exported"``, a TorchScript program, loaded only where the config says
  ``exported: true``) or a snapshot of the learner (``"snapshot"``, self-play).
* :class:`SnapshotLeague`: self-play's source of snapshots, read from the learner's checkpoint
  directory; it adds them to (and drops them from) a pool.
* A chooser, ``chooser(pool, rng) -> name | None`` (None: the env draws from its own
  ``env.kwargs.opponents``): :func:`weighted_choice` (by the entries' weights) and
  :class:`SelfPlayChooser` (a snapshot with some probability, else another chooser). The
  league service plugs its own chooser in (prioritized fictitious self-play).
* :class:`OpponentWrapper`: the gym wrapper that puts the chosen opponent into the match at
  each reset and reports each finished match as a :class:`MatchResult`.
* :func:`wrap_opponents`: what an actor calls on its envs, from ``cfg.opponents`` and
  ``cfg.selfplay``.

A frozen policy plays through the match env's ``"policy"`` opponent (``opponent_policy``): the
env gives it observations from its own side, in its own frame, like the agent's (blue sees the
field rotated by 180 degrees), so a policy trained on either side plays either side.

It lives in ``common/`` because actors (which import only ``common/``) use it.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable, Protocol

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.checkpoints import list_checkpoints, read_checkpoint
from zenrl.common.config import OpponentsConfig, RunConfig, SelfPlayConfig
from zenrl.common.errors import CheckpointError, ConfigError, ZenrlError
from zenrl.common.policy_io import ExportedPlayer, GreedyPolicy, build_network, is_exported

log = logging.getLogger(__name__)

#: prefix of the pool names of self-play snapshots (a configured name cannot contain ':')
SNAPSHOT_PREFIX = "snapshot:"


@dataclasses.dataclass(frozen=True)
class MatchResult:
    """One finished match, from the training agent's side.

    ``opponent``: the pool name of the opponent (for a draw the env made itself from
    ``env.kwargs.opponents``: the bot's name); ``side``: the agent's side ("red" / "blue");
    ``outcome``: "win" | "draw" | "loss"; scores are the judge's final ones."""

    opponent: str
    side: str
    outcome: str
    my_score: int
    enemy_score: int


@dataclasses.dataclass
class Opponent:
    """A named opponent. ``kind``: "bot" (``bot`` names the env's scripted opponent),
    "checkpoint" or "snapshot" (``net``: the frozen policy network, shared by every env of the
    process), "exported" (``player``: an ``obs -> action`` callable, shared; a mixed policy's
    envs each get a seat of their own, ``for_env``).
    ``weight``: its share in :func:`weighted_choice` (0: only drawn by name, as snapshots are);
    ``epsilon``: its random-action probability."""

    name: str
    kind: str
    weight: float = 1.0
    bot: str | None = None
    net: torch.nn.Module | None = None
    player: Callable[[Any], int] | None = None
    epsilon: float = 0.0
    source: str | None = None  # the file it came from

    def new_player(self, n_actions: int) -> Callable[[Any], int] | None:
        """A player of this opponent for one env (None for a bot): a network gets its own
        :class:`GreedyPolicy` (a recurrent one carries per-episode state)."""
        if self.net is not None:
            return GreedyPolicy(self.net, n_actions, name=self.name)
        for_env = getattr(self.player, "for_env", None)  # a mixed exported policy: a member per env
        return for_env() if for_env is not None else self.player


class OpponentPool:
    """Named opponents shared by the envs of one process. ``sources`` are called by
    :meth:`refresh` (at each episode's start) to add or drop opponents, e.g.
    :meth:`SnapshotLeague.refresh`."""

    def __init__(self, n_actions: int, entries: list[Opponent] | None = None) -> None:
        self.n_actions = int(n_actions)
        self.entries: dict[str, Opponent] = {}
        self.sources: list[Callable[[], Any]] = []
        for e in entries or []:
            self.add(e)

    def add(self, entry: Opponent) -> None:
        self.entries[entry.name] = entry

    def remove(self, name: str) -> None:
        self.entries.pop(name, None)

    def get(self, name: str) -> Opponent:
        return self.entries[name]

    def __contains__(self, name: object) -> bool:
        return name in self.entries

    def __len__(self) -> int:
        return len(self.entries)

    def names(self, kind: str | None = None) -> list[str]:
        """Names in insertion order, of one ``kind`` if given."""
        return [n for n, e in self.entries.items() if kind is None or e.kind == kind]

    def refresh(self) -> None:
        for source in self.sources:
            source()


class Chooser(Protocol):
    """Picks the opponent of the next episode: a name in ``pool``, or None for the env's own
    draw from ``env.kwargs.opponents``."""

    def __call__(self, pool: OpponentPool, rng: np.random.Generator) -> str | None: ...


def weighted_choice(pool: OpponentPool, rng: np.random.Generator) -> str | None:
    """A name drawn with probability proportional to its weight among the entries of positive
    weight; None (the env's own draw) when there is none."""
    names = [n for n, e in pool.entries.items() if e.weight > 0]
    if not names:
        return None
    w = np.array([pool.entries[n].weight for n in names], np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


class SelfPlayChooser:
    """With probability ``prob`` (once the pool holds a snapshot) a uniformly drawn snapshot,
    otherwise ``inner``'s choice."""

    def __init__(self, prob: float, inner: Chooser = weighted_choice) -> None:
        self.prob, self.inner = float(prob), inner

    def __call__(self, pool: OpponentPool, rng: np.random.Generator) -> str | None:
        snaps = pool.names("snapshot")
        if snaps and rng.random() < self.prob:
            return snaps[int(rng.integers(len(snaps)))]
        return self.inner(pool, rng)


# --------------------------------------------------------------------------------------------
# Building a pool from the config
# --------------------------------------------------------------------------------------------
def load_frozen(path: str | os.PathLike[str], exported: bool, observation_space: gym.Space,
                action_space: gym.Space, where: str) -> tuple[torch.nn.Module | None, ExportedPlayer | None]:
    """(network, None) for a checkpoint, (None, player) for an exported file (only with
    ``exported``). Every problem (a missing or unreadable file, an exported file not declared
    as such, other observation or action spaces) is a :class:`ConfigError` starting with
    ``where``."""
    p = Path(path)
    if not isinstance(action_space, gym.spaces.Discrete):
        raise ConfigError(f"{where}: a frozen policy plays through a discrete action set; this env's is {action_space}")
    if not p.is_file():
        raise ConfigError(f"{where}: {str(p)!r} does not exist")
    if is_exported(p):
        if not exported:
            raise ConfigError(f"{where}: {str(p)!r} is an exported TorchScript policy, and loading one runs the code "
                              "inside it: set exported: true for a file you trust")
        try:
            player = ExportedPlayer(p)
            player.check_spaces(observation_space, action_space)
        except ZenrlError as e:
            raise ConfigError(f"{where}: {e}") from None
        return None, player
    if exported:
        raise ConfigError(f"{where}: {str(p)!r} is not a `zenrl export` file (exported: true); a checkpoint needs "
                          "exported: false")
    try:
        return build_network(read_checkpoint(p), observation_space, action_space), None
    except CheckpointError as e:
        raise ConfigError(f"{where}: {e}") from None


def build_pool(cfg: OpponentsConfig, env: gym.Env) -> OpponentPool:
    """The pool of ``cfg.pool`` for ``env`` (a single match env): every file loaded and checked
    against the env's spaces, every bot name tried with one reset of ``env``. A bad entry is a
    :class:`ConfigError` naming it (``opponents.pool.<name>: ...``)."""
    # frozen policies need the action count (their epsilon draws); bots play any action set
    pool = OpponentPool(env.action_space.n if isinstance(env.action_space, gym.spaces.Discrete) else 0)
    if cfg.pool and not hasattr(env.unwrapped, "opponent_policy"):
        raise ConfigError(f"opponents.pool needs a match env (zenrl/BurgerWar*), not {env.spec.id if env.spec else env!r}")
    for name, spec in cfg.pool.items():
        where = f"opponents.pool.{name}"
        if spec.bot is not None:
            try:
                env.reset(seed=0, options={"opponent": spec.bot})
            except ValueError as e:
                raise ConfigError(f"{where}: bot {spec.bot!r}: {e}") from None
            pool.add(Opponent(name, "bot", spec.weight, bot=spec.bot))
            continue
        net, player = load_frozen(spec.path, spec.exported, env.observation_space, env.action_space, where)
        eps = cfg.epsilon if spec.epsilon is None else spec.epsilon
        pool.add(Opponent(name, "exported" if player is not None else "checkpoint", spec.weight, net=net,
                          player=player, epsilon=eps, source=str(spec.path)))
        log.info("opponent %s: %s %s (weight %g, epsilon %g)", name, pool.get(name).kind, spec.path, spec.weight, eps)
    return pool


def check_opponents(cfg: RunConfig, env: gym.Env) -> None:
    """Load and check ``cfg.opponents`` against ``env`` once (what ``zenrl run`` calls before it
    starts anything): :class:`ConfigError` naming the first bad entry. Frozen policies (the pool's
    and self-play's snapshots) act through a discrete action set: a continuous one is refused."""
    require_discrete_for_frozen(cfg, env.action_space, league=cfg.league.enabled)
    if cfg.opponents.pool:
        build_pool(cfg.opponents, env)


def require_discrete_for_frozen(cfg: RunConfig, action_space: gym.Space, league: bool = False) -> None:
    """Frozen policies play a match through its discrete action set (a policy's action index is
    the opponent robot's command): with a continuous one, self-play, a league or frozen policies
    in ``opponents.pool`` are a :class:`ConfigError` naming which."""
    if isinstance(action_space, gym.spaces.Discrete):
        return
    what = ("a league" if league else "selfplay" if cfg.selfplay.enabled else
            "opponents.pool's frozen policies" if any(spec.path is not None for spec in cfg.opponents.pool.values()) else None)
    if what is not None:
        raise ConfigError(f"{what} needs a discrete action set; {cfg.env.id} with env.kwargs={dict(cfg.env.kwargs)} "
                          f"has {action_space} (scripted bots play against any set)")


# --------------------------------------------------------------------------------------------
# Self-play: frozen learner snapshots
# --------------------------------------------------------------------------------------------
class SnapshotLeague:
    """Frozen copies of the learner, taken from its checkpoint directory at most every
    ``cfg.snapshot_interval_s`` (the newest checkpoint then, if not already held), at most
    ``cfg.max_snapshots`` kept (the oldest dropped first). One per actor process; its envs share
    it. With a ``pool``, every snapshot held is also in the pool as ``snapshot:<file name>``
    (kind "snapshot", weight 0, epsilon ``cfg.epsilon``). Never raises on a missing or vanishing
    checkpoint: it logs and keeps what it has.

    ``observation_space`` / ``action_space``: the single match env's spaces.
    """

    def __init__(self, cfg: SelfPlayConfig, checkpoint_dir: str | os.PathLike[str], observation_space: gym.Space,
                 action_space: gym.Space, seed: int = 0, pool: OpponentPool | None = None) -> None:
        self.cfg = cfg
        self.dir = Path(checkpoint_dir)
        self.observation_space, self.action_space = observation_space, action_space
        self.rng = np.random.default_rng(seed)
        self.pool = pool
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
                log.info("self-play: no checkpoint in %s yet; no snapshot opponents", self.dir)
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
        for name, _ in self.snapshots[:-self.cfg.max_snapshots]:
            if self.pool is not None:
                self.pool.remove(SNAPSHOT_PREFIX + name)
        del self.snapshots[:-self.cfg.max_snapshots]
        if self.pool is not None:
            self.pool.add(Opponent(SNAPSHOT_PREFIX + newest.name, "snapshot", 0.0, net=net, epsilon=self.cfg.epsilon,
                                   source=str(newest)))
        log.info("self-play: snapshot %s added (%d held)", newest.name, len(self.snapshots))
        return True

    def sample(self) -> tuple[str, torch.nn.Module] | None:
        """A uniformly drawn snapshot, or None while the league is empty."""
        if not self.snapshots:
            return None
        return self.snapshots[int(self.rng.integers(len(self.snapshots)))]


# --------------------------------------------------------------------------------------------
# The wrapper
# --------------------------------------------------------------------------------------------
class _Seat:
    """The env's ``opponent_policy``: forwards each observation (the opponent's own) to the
    episode's frozen player, whose action is replaced by a random one with probability
    ``epsilon`` (drawn from the seat's own generator). The player sees every observation, so a
    recurrent one keeps its state."""

    def __init__(self, n_actions: int, seed: int) -> None:
        self.n_actions = int(n_actions)
        self.rng = np.random.default_rng(seed)
        self.player: Callable[[Any], int] | None = None
        self.epsilon = 0.0

    def sit(self, player: Callable[[Any], int], epsilon: float) -> None:
        self.player, self.epsilon = player, float(epsilon)
        reseed = getattr(player, "reseed", None)
        if reseed is not None:  # what a player draws (a mixed policy's member) follows the seat's seed
            reseed(int(self.rng.integers(2**63)))
        reset = getattr(player, "reset", None)
        if reset is not None:
            reset()  # a recurrent policy starts the episode from a zero state

    def __call__(self, obs: Any) -> int:
        if self.player is None:
            raise RuntimeError("no frozen opponent seated for this episode")
        a = int(self.player(obs))
        if self.epsilon > 0 and self.rng.random() < self.epsilon:
            return int(self.rng.integers(self.n_actions))
        return a


class OpponentWrapper(gym.Wrapper):
    """Per-episode opponent choice for a ``zenrl/BurgerWar*`` env. At each reset the pool is
    refreshed and ``chooser`` names the episode's opponent (an explicit ``options["opponent"]``
    wins; None leaves the draw to the env's ``env.kwargs.opponents``); a frozen policy plays as
    the env's ``"policy"`` opponent. When a match ends (a step whose info has ``outcome``),
    ``on_result`` gets its :class:`MatchResult`. Observations, rewards and the rest pass through.

    ``opponent``: the pool name of the current episode's opponent.
    """

    def __init__(self, env: gym.Env, pool: OpponentPool, chooser: Chooser = weighted_choice, seed: int = 0,
                 on_result: Callable[[MatchResult], None] | None = None) -> None:
        super().__init__(env)
        self.pool, self.chooser, self.on_result = pool, chooser, on_result
        self.rng = np.random.default_rng(seed)
        self.seat = _Seat(pool.n_actions, seed + 1)
        self.opponent: str | None = None
        self._players: dict[str, tuple[Opponent, Callable[[Any], int] | None]] = {}
        # the env builds its "policy" opponent lazily from this attribute on the first episode
        # that names it (documented option ``opponent_policy``)
        env.unwrapped.opponent_policy = self.seat

    def _player(self, entry: Opponent) -> Callable[[Any], int] | None:
        held = self._players.get(entry.name)
        if held is None or held[0] is not entry:  # a snapshot name can come back with another network
            held = (entry, entry.new_player(self.pool.n_actions))
            self._players = {n: v for n, v in self._players.items() if n in self.pool}
            self._players[entry.name] = held
        return held[1]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.pool.refresh()
        options = dict(options or {})
        name = None
        if "opponent" not in options:
            name = self.chooser(self.pool, self.rng)
            if name is not None:
                if name not in self.pool:
                    raise ValueError(f"the opponent chooser picked {name!r}, which is not in the pool "
                                     f"({', '.join(self.pool.names()) or 'empty'})")
                entry = self.pool.get(name)
                if entry.kind == "bot":
                    options["opponent"] = entry.bot
                else:
                    self.seat.sit(self._player(entry), entry.epsilon)
                    options["opponent"] = "policy"
        obs, info = self.env.reset(seed=seed, options=options)
        self.opponent = name if name is not None else info.get("opponent", options.get("opponent"))
        return obs, info

    def step(self, action):
        obs, r, term, trunc, info = self.env.step(action)
        if (term or trunc) and self.on_result is not None and "outcome" in info:
            self.on_result(MatchResult(str(self.opponent), str(info.get("side")), info["outcome"],
                                       int(info["my_score"]), int(info["enemy_score"])))
        return obs, r, term, trunc, info


class ResultTally:
    """The default ``on_result`` of an actor: wins / draws / losses per opponent, logged as one
    line at the first result and then at most every ``log_every_s`` seconds (``counts``: name ->
    [wins, draws, losses])."""

    def __init__(self, log_every_s: float = 60.0) -> None:
        self.counts: dict[str, list[int]] = {}
        self.log_every_s = float(log_every_s)
        self._next_log = 0.0

    def __call__(self, result: MatchResult) -> None:
        c = self.counts.setdefault(result.opponent, [0, 0, 0])
        c[("win", "draw", "loss").index(result.outcome)] += 1
        if time.monotonic() >= self._next_log:
            self._next_log = time.monotonic() + self.log_every_s
            log.info("matches by opponent (W/D/L): %s", ", ".join(f"{n} {w}/{d}/{l_}" for n, (w, d, l_) in self.counts.items()))


def wrap_opponents(envs: list[gym.Env], cfg: RunConfig, run_id: str, seed: int, chooser: Chooser | None = None,
                   on_result: Callable[[MatchResult], None] | None = None) -> list[gym.Env]:
    """An actor's envs with their opponents from the config: ``cfg.opponents.pool`` (drawn by
    weight) and, with ``cfg.selfplay.enabled``, snapshots of the learner read from
    ``cfg.selfplay.checkpoint_dir`` (default ``<runs_dir>/<run_id>/checkpoints``, the learner's, on
    a shared filesystem) with probability ``selfplay.snapshot_prob``. All envs share one pool;
    ``chooser`` replaces the config's choice (e.g. a league's); ``on_result`` gets every finished
    match (default: a :class:`ResultTally` that logs them). The envs come back unwrapped when
    there is nothing to wrap. A bad pool entry is a :class:`ConfigError` (at start)."""
    if not cfg.opponents.pool and not cfg.selfplay.enabled and chooser is None:
        return envs
    require_discrete_for_frozen(cfg, envs[0].action_space, league=chooser is not None)
    pool = build_pool(cfg.opponents, envs[0])
    pick: Chooser = weighted_choice
    if cfg.selfplay.enabled:
        sp = cfg.selfplay
        ckpt_dir = Path(sp.checkpoint_dir) if sp.checkpoint_dir else Path(cfg.runs_dir) / run_id / "checkpoints"
        league = SnapshotLeague(sp, ckpt_dir, envs[0].observation_space, envs[0].action_space, seed, pool)
        pool.sources.append(league.refresh)
        pick = SelfPlayChooser(sp.snapshot_prob, pick)
    on_result = on_result if on_result is not None else ResultTally()
    return [OpponentWrapper(e, pool, chooser or pick, seed + 7919 * (i + 1), on_result) for i, e in enumerate(envs)]
