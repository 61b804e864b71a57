"""How an actor picks its actions: one batched forward per step on flat observations
``{name: array[E, ...]}``, giving int64[E] actions and the extras its adder needs.

* :class:`EpsilonGreedyQ` (Ape-X): per-env epsilon from the Ape-X ladder over argmax Q; the Q
  values go to the adder, which reuses them for the initial priorities.
* :class:`Sampling` (A3C, IMPALA): actions drawn from an actor-critic's softmax policy; with
  ``with_logp`` (IMPALA) the extras are the behaviour log-probabilities of the actions drawn.
* :class:`Demonstrated` (Ape-X): a demonstrator's action in place of the policy's, now and then
  (``actor.guard_share``: the match env's guard as a teacher).
* :class:`Greedy` (evaluation): argmax of the Q values or of the policy logits.
* :class:`RecurrentEpsilonGreedyQ` (R2D2) and :class:`RecurrentGreedy` (its evaluation): the
  same over a recurrent Q network, with a state per env zeroed where an episode begins
  (:class:`RecurrentQPolicy`; the adder wrapper :class:`EpisodeStartsToPolicy` tells it where).

A policy acts with the network the weights follower loads into (``net``); the worker calls
:meth:`sync` after each load. For MLP networks the forward runs in numpy (:class:`NumpyQ`, the
same values as the network's forward to float32 rounding): torch's per-op dispatch costs more
than the arithmetic of the small MLPs actors run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol

import numpy as np
import torch

from zenrl.common.exploration import EpsilonGreedy
from zenrl.common.networks import NumpyQ, gaussian_logp, sample_categorical, to_tensors
from zenrl.common.policy_io import greedy_actions, sampled_actions
from zenrl.common.recurrent import NumpyRecurrentQ, RecurrentQNetwork

Obs = Mapping[str, np.ndarray]


class Policy(Protocol):
    """What :class:`~zenrl.actor.worker.ActorWorker` asks of a policy."""

    net: torch.nn.Module

    def act(self, obs: Obs) -> tuple[np.ndarray, Any]:
        """int64[E] actions for flat observations [E, ...], and the extras for the adder."""

    def sync(self) -> None:
        """``net``'s weights changed (a numpy copy must follow)."""

    def reseed(self, seed: int) -> None:
        """Restart the policy's random stream (an evaluation round is reproducible)."""


class QForward:
    """float32[B, A] outputs of ``net`` (Q values, or an actor-critic's logits) for flat
    observations [B, ...], in numpy where the network is an MLP."""

    def __init__(self, net: torch.nn.Module, use_numpy: bool = True) -> None:
        self.net = net
        self.fast = NumpyQ.of(net) if use_numpy else None

    def sync(self) -> None:
        if self.fast is not None:
            self.fast.load(self.net)

    def __call__(self, obs: Obs) -> np.ndarray:
        if self.fast is not None:
            return self.fast(obs)
        with torch.no_grad():
            out = self.net(to_tensors(obs))
        return (out[0] if isinstance(out, tuple) else out).numpy()


def _explore(actions: np.ndarray, epsilon: float, n_actions: int, rng: np.random.Generator) -> np.ndarray:
    """Each of the E ``actions`` replaced by a uniform one with probability ``epsilon``: an index
    in ``0..n_actions-1``, or for continuous actions float32[E, d] a point of [-1, 1]^d."""
    if epsilon > 0:
        r = rng.random(actions.shape[0]) < epsilon
        if actions.ndim == 2:
            actions[r] = rng.uniform(-1.0, 1.0, (int(r.sum()), actions.shape[1]))
        else:
            actions[r] = rng.integers(0, n_actions, int(r.sum()))
    return actions


def _log_std(net: torch.nn.Module) -> np.ndarray:
    """float64[d]: a Gaussian actor-critic's clamped log standard deviation."""
    with torch.no_grad():
        return net.clamped_log_std().double().cpu().numpy()


class EpsilonGreedyQ:
    """Ape-X acting: env i acts at random with probability ``eps[i]`` (float64[E], its rung of
    the ladder), else greedily on Q. Extras: the float32[E, A] Q values acted on."""

    def __init__(self, net: torch.nn.Module, eps: np.ndarray, n_actions: int, rng: np.random.Generator) -> None:
        self.net = net
        self.eps = eps
        self.q = QForward(net)
        self._pick = EpsilonGreedy(eps, n_actions, rng)

    def sync(self) -> None:
        self.q.sync()

    def reseed(self, seed: int) -> None:
        self._pick.rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> tuple[np.ndarray, np.ndarray]:
        q = self.q(obs)
        return self._pick(q), q

    def values(self, obs: Obs) -> np.ndarray:
        """float[B] ``max_a Q(s, a)`` (the n-step builder's bootstrap of truncated episodes)."""
        return self.q(obs).max(1)


class Demonstrated:
    """An Ape-X policy with a demonstrator: where ``rule(obs)`` (int64[E], -1 where it has no
    action) gives an action for env i, that action replaces the inner policy's with probability
    ``share``. ``act`` returns the actions taken, so the transitions record what was done and
    off-policy Q-learning learns the value of the demonstrated actions next to the policy's
    own; the extras (the Q values acted on) pass through. ``taken`` counts the replaced actions."""

    def __init__(self, inner: EpsilonGreedyQ, rule: Callable[[Obs], np.ndarray], share: float,
                 rng: np.random.Generator) -> None:
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"a demonstrator's share must be in [0, 1], got {share!r}")
        self.inner, self.rule, self.share, self.rng = inner, rule, float(share), rng
        self.taken = 0

    def sync(self) -> None:
        self.inner.sync()

    def reseed(self, seed: int) -> None:
        self.inner.reseed(seed)
        self.rng = np.random.default_rng([seed, 1])

    def act(self, obs: Obs) -> tuple[np.ndarray, np.ndarray]:
        actions, extras = self.inner.act(obs)
        shown = np.asarray(self.rule(obs), np.int64)
        take = (shown >= 0) & (self.rng.random(shown.shape[0]) < self.share)
        if take.any():
            actions = np.where(take, shown, actions)
            self.taken += int(take.sum())
        return actions, extras

    def values(self, obs: Obs) -> np.ndarray:
        return self.inner.values(obs)


class Greedy:
    """Argmax actions of a Q network or an actor-critic (evaluation), with ``epsilon`` uniform
    actions from its own generator. The selection is :func:`~zenrl.common.policy_io.greedy_actions`
    (what the tools and self-play use); an MLP network takes the numpy route to the same
    argmax. A Gaussian actor-critic's greedy action is its mean, float32[E, d]. No extras."""

    def __init__(self, net: torch.nn.Module, n_actions: int, epsilon: float = 0.0, seed: int = 0,
                 use_numpy: bool = True) -> None:
        self.net = net
        self.n_actions, self.epsilon = n_actions, epsilon
        self.rng = np.random.default_rng(seed)
        self.q = QForward(net, use_numpy)

    def sync(self) -> None:
        self.q.sync()

    def reseed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> tuple[np.ndarray, None]:
        if getattr(self.net, "continuous", False):
            a = self.q(obs).astype(np.float32)
        else:
            a = greedy_actions(self.net, obs) if self.q.fast is None else self.q(obs).argmax(1)
        return _explore(a, self.epsilon, self.n_actions, self.rng), None


class Sampling:
    """Actions drawn from an actor-critic's categorical policy (A3C acting; evaluation with
    ``evaluator.policy: sample``), with ``epsilon`` uniform actions. No extras, unless
    ``with_logp`` (IMPALA): then the extras are float32[E] ``log mu(a|x)``, the log-probability
    of each action under the policy that drew it (the epsilon mixture included), which the
    learner's V-trace corrects with. ``use_numpy``: an MLP network's logits come from the numpy
    forward (:class:`QForward`), the Gumbel-max draw from the same float64 logits either way.

    A Gaussian actor-critic (continuous actions): float32[E, d] actions ``mean + std * N(0, 1)``
    (normalised units; the env clips them to [-1, 1]), the log-density of the float32 action as
    the extras; epsilon then draws uniform points of [-1, 1]^d, and cannot come with
    ``with_logp`` (the mixture has no density the learner could use)."""

    def __init__(self, net: torch.nn.Module, n_actions: int, rng: np.random.Generator, epsilon: float = 0.0,
                 use_numpy: bool = False, with_logp: bool = False) -> None:
        self.net = net
        self.n_actions, self.epsilon, self.rng = n_actions, epsilon, rng
        self.with_logp = with_logp
        self.continuous = bool(getattr(net, "continuous", False))
        if self.continuous and with_logp and epsilon > 0:
            raise ValueError("a Gaussian policy's behaviour log-densities cannot include epsilon-uniform actions")
        self.q = QForward(net, use_numpy) if (use_numpy or with_logp or self.continuous) else None
        self._log_std = _log_std(net) if self.continuous else None

    def sync(self) -> None:
        if self.q is not None:
            self.q.sync()
        if self.continuous:
            self._log_std = _log_std(self.net)

    def reseed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> tuple[np.ndarray, np.ndarray | None]:
        if self.continuous:
            return self._act_gaussian(obs)
        if self.q is None:
            return _explore(sampled_actions(self.net, obs, self.rng), self.epsilon, self.n_actions, self.rng), None
        z = self.q(obs).astype(np.float64)
        a = _explore(sample_categorical(z, self.rng), self.epsilon, self.n_actions, self.rng)
        if not self.with_logp:
            return a, None
        z -= z.max(axis=1, keepdims=True)
        logp = z[np.arange(len(a)), a] - np.log(np.exp(z).sum(axis=1))
        if self.epsilon > 0:  # a ~ (1 - eps) pi + eps uniform
            logp = np.log((1.0 - self.epsilon) * np.exp(logp) + self.epsilon / self.n_actions)
        return a, logp.astype(np.float32)

    def _act_gaussian(self, obs: Obs) -> tuple[np.ndarray, np.ndarray | None]:
        mean = self.q(obs).astype(np.float64)
        a = (mean + np.exp(self._log_std) * self.rng.standard_normal(mean.shape)).astype(np.float32)
        if not self.with_logp:
            return _explore(a, self.epsilon, self.n_actions, self.rng), None
        # the density of the float32 action sent, as the learner will evaluate it
        return a, gaussian_logp(mean, self._log_std, a.astype(np.float64)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Recurrent policies (R2D2): a state per env, zeroed where an episode begins
# --------------------------------------------------------------------------------------------
class RecurrentQForward:
    """Q values and the next state of a :class:`~zenrl.common.recurrent.RecurrentQNetwork` for
    flat observations [B, ...] and a state (h, c) float32[B, H] each: q float32[B, A] and the
    state after the step. In numpy (:class:`~zenrl.common.recurrent.NumpyRecurrentQ`) for MLP
    encoders, with ``net.step`` otherwise."""

    def __init__(self, net: RecurrentQNetwork, use_numpy: bool = True) -> None:
        self.net = net
        self.fast = NumpyRecurrentQ.of(net) if use_numpy else None

    def sync(self) -> None:
        if self.fast is not None:
            self.fast.load(self.net)

    def __call__(self, obs: Obs, state: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        if self.fast is not None:
            return self.fast(obs, state)
        with torch.no_grad():
            q, (h, c) = self.net.step(to_tensors(obs), (torch.from_numpy(state[0]), torch.from_numpy(state[1])))
        return q.numpy(), (h.numpy(), c.numpy())


@dataclass
class RecurrentExtras:
    """What a recurrent Q policy hands its adder per step: the float32[E, A] Q values acted on
    and the state (h, c) float32[E, H] each they were computed from (zero where an episode began)."""

    q: np.ndarray
    h: np.ndarray
    c: np.ndarray


class RecurrentQPolicy:
    """The state a recurrent Q policy carries: (h, c) float32[E, H] per env after its last step,
    and which envs begin an episode at the next step (their state is zeroed then). The worker
    gives policies observations only, so the episode starts come from
    :class:`EpisodeStartsToPolicy`, which wraps the adder (every env begins one at the first
    step)."""

    def __init__(self, net: RecurrentQNetwork, use_numpy: bool = True) -> None:
        self.net = net
        self.q = RecurrentQForward(net, use_numpy)
        self.state: tuple[np.ndarray, np.ndarray] | None = None
        self.starts: np.ndarray | None = None

    def sync(self) -> None:
        self.q.sync()

    def episodes_ended(self, done: np.ndarray | None) -> None:
        """The envs where ``done`` (bool[E]) is set begin an episode at the next step; None: all of
        them (a new round of episodes)."""
        if self.starts is not None:
            self.starts |= True if done is None else done

    def step(self, obs: Obs) -> RecurrentExtras:
        """One step of every env from its state (zero where an episode begins); keeps the new state."""
        E = len(next(iter(obs.values())))
        if self.state is None or self.state[0].shape[0] != E:
            z = np.zeros((E, self.net.lstm_size), np.float32)
            self.state, self.starts = (z, z.copy()), np.ones(E, bool)
        h, c = self.state
        if self.starts.any():
            keep = ~self.starts[:, None]
            h, c = h * keep, c * keep
            self.starts[:] = False
        q, self.state = self.q(obs, (h, c))
        return RecurrentExtras(q, h, c)

    def q_after(self, obs: Obs, idx: np.ndarray) -> np.ndarray:
        """float32[len(idx), A]: the Q values of envs ``idx`` on ``obs`` (their rows; e.g. the
        final observations of truncated episodes) from the state their last step left."""
        return self.q({k: v[idx] for k, v in obs.items()}, (self.state[0][idx], self.state[1][idx]))[0]


class RecurrentEpsilonGreedyQ(RecurrentQPolicy):
    """R2D2 acting: :class:`EpsilonGreedyQ` (per-env epsilon, the Ape-X ladder) over a recurrent
    Q network. Extras: :class:`RecurrentExtras` (the Q values feed the initial priorities, the
    state is stored with each sequence)."""

    def __init__(self, net: RecurrentQNetwork, eps: np.ndarray, n_actions: int, rng: np.random.Generator,
                 use_numpy: bool = True) -> None:
        super().__init__(net, use_numpy)
        self.eps = eps
        self._pick = EpsilonGreedy(eps, n_actions, rng)

    def reseed(self, seed: int) -> None:
        self._pick.rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> tuple[np.ndarray, RecurrentExtras]:
        x = self.step(obs)
        return self._pick(x.q), x


class RecurrentGreedy(RecurrentQPolicy):
    """Evaluation of a recurrent Q network: argmax actions carrying each env's state through its
    episode, with ``epsilon`` uniform actions from its own generator. No extras."""

    def __init__(self, net: RecurrentQNetwork, n_actions: int, epsilon: float = 0.0, seed: int = 0,
                 use_numpy: bool = True) -> None:
        super().__init__(net, use_numpy)
        self.n_actions, self.epsilon = n_actions, epsilon
        self.rng = np.random.default_rng(seed)

    def reseed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> tuple[np.ndarray, None]:
        return _explore(self.step(obs).q.argmax(1), self.epsilon, self.n_actions, self.rng), None


class EpisodeStartsToPolicy:
    """An adder that tells a :class:`RecurrentQPolicy` where episodes begin, then hands each step
    on to ``inner``: envs whose episode the step ended (``EnvBatch`` has reset them), and every
    env after a step that ends a round (the worker resets them all)."""

    def __init__(self, inner: Any, policy: RecurrentQPolicy) -> None:
        self.inner, self.policy = inner, policy

    def start(self, node: Any) -> None:
        self.inner.start(node)

    def add(self, obs: Obs, actions: np.ndarray, extras: Any, res: Any) -> bool:
        try:
            ended = self.inner.add(obs, actions, extras, res)
        finally:  # the envs were stepped (and reset) whatever the inner adder did
            self.policy.episodes_ended(res.terminated | res.truncated)
        if ended:
            self.policy.episodes_ended(None)
        return ended

    def flush(self) -> None:
        self.inner.flush()

    def values(self) -> dict[str, Any]:
        return self.inner.values()
