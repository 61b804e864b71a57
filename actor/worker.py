"""The one actor worker: E envs stepped as a batch by a policy, each step handed to an adder,
the learner's newest weights followed between steps. The Ape-X actor, the A3C worker and the
evaluator are three compositions of it (``actor/service.py``, ``actor/a3c.py``,
``actor/evaluator.py``)::

    policy  (actor/policies.py)  obs -> actions (+ extras: the Q values for the priorities)
    adder   (actor/adders.py)    each step -> n-step transitions to the replay | rollout
                                 gradients | evaluation episodes
    weights (actor/weights.py)   the newest broadcast, loaded between steps, never blocking
    gate                         when acting may begin: at once | once weights arrived |
                                 a round per interval on new weights (evaluation)

It is a :class:`~zenrl.common.roles.Worker`: :class:`~zenrl.common.roles.RoleLoop` owns the
liveliness token, the stats cadence, the budget wait, the orderly stop and supervision; one
:meth:`ActorWorker.step` is one batched env step.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Protocol

import numpy as np

from zenrl.actor.adders import Adder
from zenrl.actor.batch_env import EnvBatch
from zenrl.actor.pacing import StepPacer
from zenrl.actor.policies import Policy
from zenrl.actor.weights import WeightsFollower
from zenrl.common import protocol as P
from zenrl.common.league_client import LeagueChooser
from zenrl.common.opponents import wrap_opponents
from zenrl.common.roles import Cadence, RoleLoop

log = logging.getLogger(__name__)


class Gate(Protocol):
    def due(self, weights: WeightsFollower, timeout_s: float) -> bool:
        """May acting (a new round) begin now? Waits at most ``timeout_s`` for that."""


class AtOnce:
    """Act from the first step, with the seeded initial weights until the learner's arrive
    (Ape-X: the learner starts from the same seed)."""

    def due(self, weights: WeightsFollower, timeout_s: float) -> bool:
        return True


class FirstWeights:
    """Act once the learner's weights arrived (A3C: gradients are taken at a version).
    ``query_timeout_s`` bounds one ask of the learner."""

    def __init__(self, query_timeout_s: float) -> None:
        self.query_timeout_s = query_timeout_s

    def due(self, weights: WeightsFollower, timeout_s: float) -> bool:
        return weights.await_first(min(timeout_s, self.query_timeout_s))


class EvalInterval:
    """A round starts ``interval_s`` after the last one started, once weights newer than the
    last round's are loaded (weights not newer: look again ``retry_s`` later)."""

    def __init__(self, interval_s: float, retry_s: float = 0.5) -> None:
        self.interval_s, self.retry_s = interval_s, retry_s
        self.next_t = time.monotonic()
        self.evaluated = -1

    def due(self, weights: WeightsFollower, timeout_s: float) -> bool:
        wait = self.next_t - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, timeout_s))
            return False
        if weights.version < 0 or weights.version == self.evaluated:
            self.next_t = time.monotonic() + self.retry_s
            return False
        self.evaluated = weights.version
        self.next_t = time.monotonic() + self.interval_s
        return True


def match_opponents(envs: EnvBatch, cfg: Any, node: Any, run_id: str, actor_id: str, slot: int,
                    make_net: Callable[[], Any]) -> LeagueChooser | None:
    """Wrap ``envs`` (in place) with their match opponents: ``opponents.pool`` and self-play
    snapshots (common/opponents.py), or, in a league run (``league.player`` set by ``zenrl run``),
    the league's choice of each match's opponent, to which every result is reported
    (common/league_client.py). ``make_net()``: a fresh network of this actor's architecture (a
    league opponent's weights are loaded into one). Returns the league chooser, or None."""
    league = LeagueChooser(cfg, node, actor_id, make_net) if cfg.league.player else None
    envs.envs = wrap_opponents(envs.envs, cfg, run_id, seed=cfg.seed + 31 * (slot + 1), chooser=league,
                               on_result=None if league is None else league.report)
    return league


class ActorWorker:
    """Acting composed from a policy, an adder, the weights follower and a gate.

    ``poll_steps``: load new weights every this many batched steps (None: only between
    rounds, so a round plays one version). ``round_seed(k)``: the seed envs and policy restart
    from at the k-th round (None: the envs reset once, from their own seed, and the policy's
    stream runs on). ``pacer``: a cap on env steps per second. ``episode_epsilon`` not None:
    finished training episodes are published on ``episodes/<id>`` with that epsilon.
    ``max_steps``: a budget of batched steps (then :meth:`done`)."""

    role = "actor"
    #: a league run's chooser (:func:`match_opponents`), set by the composition before this
    #: class's ``__init__``: it reports each result with the weights version acted with
    league: LeagueChooser | None = None

    def __init__(self, keys: P.Keys, worker_id: str, slot: int | None, envs: EnvBatch, policy: Policy,
                 adder: Adder, weights: WeightsFollower, gate: Gate, *, poll_steps: int | None,
                 report_s: float, query_timeout_s: float, round_seed: Callable[[int], int] | None = None,
                 pacer: StepPacer | None = None,
                 episode_epsilon: float | None = None, max_steps: int | None = None) -> None:
        self.keys, self.id, self.slot = keys, worker_id, slot
        self.envs, self.policy, self.adder, self.weights, self.gate = envs, policy, adder, weights, gate
        self.poll_steps, self.report_s, self.query_timeout_s = poll_steps, report_s, query_timeout_s
        self.round_seed, self.pacer, self.episode_epsilon = round_seed, pacer, episode_epsilon
        self.max_steps = max_steps
        if self.league is not None:
            self.league.version_fn = lambda: weights.version
        self.steps = 0          # batched steps
        self.env_steps = 0
        self.rounds = 0
        self._obs: dict[str, np.ndarray] | None = None
        self._due: float | None = None
        self._ep_returns: list[float] = []
        self._ep_lengths: list[int] = []
        self._eps_pub: Any = None

    # -- the Worker interface -----------------------------------------------------------------
    def start(self, node: Any, sup: Any = None) -> None:
        self.adder.start(node)
        if self.episode_epsilon is not None:
            self._eps_pub = node.publisher(self.keys.episodes(self.id))
        if self.weights.fetch_initial(min(2.0, self.query_timeout_s)):
            self.policy.sync()
            log.info("%s %s starts with weights version %d", self.role, self.id, self.weights.version)

    def step(self, timeout_s: float) -> bool:
        """One batched env step (False: none yet, waiting for the gate or the pacer)."""
        if self._obs is None and not self._begin(timeout_s):
            return False
        if self.pacer is not None and not self._paced(timeout_s):
            return False
        if self.poll_steps is not None and self.steps % self.poll_steps == 0:
            self._load_weights()
        obs = self._obs
        actions, extras = self.policy.act(obs)
        res = self.envs.step(actions)
        self.steps += 1
        self.env_steps += self.envs.num_envs
        self._obs = res.obs  # before the adder: the envs moved on even if it fails
        if self.episode_epsilon is not None:
            self._ep_returns += res.ep_returns
            self._ep_lengths += res.ep_lengths
        if self.adder.add(obs, actions, extras, res):
            self._obs = None  # the round is over: the next step begins another
        return True

    def done(self) -> bool:
        return self.max_steps is not None and self.steps >= self.max_steps

    def progress(self) -> int:
        return self.env_steps

    def report(self, interval_s: float) -> tuple[dict[str, Any], str | None]:
        self._publish_episodes()
        vals = self.adder.values()
        vals.update(self.envs.values())
        vals.update({"env_steps": self.env_steps, "policy_version": self.weights.version,
                     "weights_rejected": self.weights.rejected})
        if self.slot is not None:
            vals["slot"] = self.slot
        if self.league is not None:
            vals.update(self.league.values())
        return vals, None

    def save(self) -> None:
        pass  # an actor holds no training state

    def close(self) -> None:
        try:
            self.adder.flush()
            self._publish_episodes()
        finally:
            self.envs.close()

    def run_loop(self, node: Any, stop: threading.Event) -> None:
        """Act until ``stop`` in :class:`~zenrl.common.roles.RoleLoop` (in this thread: torch's
        thread setting is per thread)."""
        RoleLoop(node, self.keys, self.role, self.id, Cadence(log_interval_s=self.report_s)).run(self, stop)

    # -- parts of a step ----------------------------------------------------------------------
    def _load_weights(self) -> None:
        if self.weights.maybe_load():
            self.policy.sync()

    def _begin(self, timeout_s: float) -> bool:
        """Start acting (or a round): the gate opens, the envs reset."""
        self._load_weights()
        if not self.gate.due(self.weights, timeout_s):
            return False
        self.policy.sync()  # the gate may have loaded weights
        if self.round_seed is not None:
            seed = self.round_seed(self.rounds)
            self.envs.seed = seed
            self.policy.reseed(seed)
        self.rounds += 1
        self._obs = self.envs.reset()
        return True

    def _paced(self, timeout_s: float) -> bool:
        """True when the next step is due under the pacer's cap (waits at most ``timeout_s``)."""
        now = time.monotonic()
        if self._due is None:
            self._due = now + self.pacer.delay()
        if now < self._due:
            time.sleep(min(self._due - now, timeout_s))
            if time.monotonic() < self._due:
                return False
        self._due = None
        return True

    def _publish_episodes(self) -> None:
        if self._eps_pub is None or not self._ep_returns:
            return
        self._eps_pub.put(P.EpisodeStats(actor_id=self.id, slot=int(self.slot or 0),
                                         epsilon=float(self.episode_epsilon), policy_version=self.weights.version,
                                         env_steps=self.env_steps, returns=np.array(self._ep_returns, np.float32),
                                         lengths=np.array(self._ep_lengths, np.int64)).encode())
        self._ep_returns, self._ep_lengths = [], []
