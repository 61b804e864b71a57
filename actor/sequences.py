"""Fixed-length sequences for R2D2, cut from E envs stepped together, with initial priorities.

Each env's episode is cut into sequences of ``length`` = m steps that start every P = m/2 steps
(episode steps 0, P, 2P, ...), so neighbours overlap by exactly m/2 steps. A sequence never spans
two episodes: the episode's end closes it early, padded to m and masked. At an episode's end two
sequences are open (starts s0 = s1 - P and s1); the later one holds only steps that the earlier
one holds too, with its burn-in before them, so it is dropped: only s0 is emitted (s1 alone
when the episode is shorter than P). With a learner burn-in k <= m/2, every step after an
episode's first k is then trained exactly once with k = m/2 (the episode's first sequence is
trained from step 0: its start state is exactly zero).

A sequence (fields as :mod:`zenrl.learner.r2d2_loss` reads them; S sequences per block)::

    obs / obs/<key>  [S, m+1, ...]  s_0..s_m; s_len follows the last valid step: the next
                                    observation, or the final one where the episode ended
    action int64[S, m]  reward float32[S, m]  terminated, truncated, mask bool[S, m]
    first bool[S]       h, c float32[S, H]    the state the actor acted on s_0 with

Initial priority: the learner's formula (n-step returns shortened at the sequence's end, value
rescaling, ``eta max|delta| + (1 - eta) mean|delta|`` over the steps the learner trains) with
the acting network's Q values for every term: Q(s_t, a_t) and ``V(s) = max_a Q(s, a)`` from the
forward pass made when acting on s, as the Ape-X actor does (:mod:`zenrl.actor.nstep`). A
sequence closed by a truncation bootstraps from its final observation, which nobody acted on:
for those the caller's ``final_q_fn`` runs one extra step.

Frame mode (``frame_stack`` not None, image envs; docs/protocol.md): the observations leave as
frame ids, ``obs/<key>`` int64[S, m+1] (each observation one frame) or int64[S, m+1, k] (stacks
of k), one id naming the frame of every observation table; each frame is numbered once
(:class:`~zenrl.actor.frame_ids.FrameNumbering`) and travels once, in the block that follows its
recording (:attr:`SequenceBlock.frames`), so overlapping sequences and neighbouring stacks share
it. The padding after s_len repeats s_len's ids (a frame the replay holds), not zeros.

Steps live in a ring of m + block_steps rows shared by the envs (a row per batched step);
closed sequences are gathered from it every ``block_steps`` steps with one fancy index per field.
:meth:`SequenceBuilder.flush` gathers the closed ones at shutdown; open ones are dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from zenrl.actor.frame_ids import FrameNumbering
from zenrl.common.recurrent import inverse_value_rescale, mixed_priority, value_rescale

#: frame mode: the ring field of the observations' frame ids
FRAME_IDS = "frame_ids"

#: indices of the envs whose episode was truncated (and not terminated: with both flags set the
#: episode terminated, nothing to bootstrap) -> float[len(idx), A] the Q values of their
#: final observations (one step of the acting network from the state after the last step)
FinalQFn = Callable[[np.ndarray], np.ndarray]


@dataclass
class SequenceBlock:
    """Sequences closed at one step. ``data``: the fields above; ``q`` float32[S, m+1, A] the
    acting Q values (row ``len``: the bootstrap's, zeros where terminated); ``priorities``
    float32[S]; ``env``, ``start`` (episode step of s_0), ``length`` int64[S]. Frame mode:
    ``frames`` ``{table: [F, ...]}`` the frames numbered since the previous block, ids
    ``frame_base .. frame_base + F - 1``."""

    data: dict[str, np.ndarray]
    q: np.ndarray
    priorities: np.ndarray
    env: np.ndarray
    start: np.ndarray
    length: np.ndarray
    frames: dict[str, np.ndarray] | None = None
    frame_base: int = 0

    def __len__(self) -> int:
        return int(self.env.shape[0])


class SequenceBuilder:
    """Records one batched step per :meth:`add`; every ``block_steps`` steps :meth:`add` returns
    the sequences closed since the last block (a :class:`SequenceBlock`, or None if none did):
    the gathering and the priorities' ~40 numpy calls then cost once per block, not per step."""

    def __init__(self, num_envs: int, length: int, n_step: int, gamma: float, burn_in: int = 0,
                 eta: float = 0.9, eps: float = 1e-3, block_steps: int = 1, frame_stack: int | None = None) -> None:
        if length < 2 or length % 2:
            raise ValueError(f"sequence length must be even and >= 2, got {length}")
        if not 0 <= burn_in <= length // 2 or n_step < 1 or block_steps < 1:
            raise ValueError(f"need 0 <= burn_in <= length/2, n_step >= 1, block_steps >= 1, "
                             f"got {burn_in}, {n_step}, {block_steps}")
        self.E, self.m, self.P, self.n, self.K = num_envs, length, length // 2, n_step, block_steps
        self.gamma, self.burn_in, self.eta, self.eps = gamma, burn_in, eta, eps
        self.W = length + block_steps             # ring rows: a sequence's steps, s_m, the wait
        self.t = 0                                # batched steps recorded
        self.ep = np.zeros(num_envs, np.int64)    # episode step of the current step, per env
        self._ring: dict[str, np.ndarray] | None = None
        self._final: dict[str, np.ndarray] = {}   # s_len and its q where an episode ended, by row
        # closed sequences not yet gathered, per step: env, start, length, ended, and t0 (the
        # batched step of s_0, its ring row)
        self._pending: list[tuple[np.ndarray, ...]] = []
        #: frame mode: the numbering of the observations' frames (None: full observations)
        self.frames = None if frame_stack is None else FrameNumbering(num_envs, frame_stack)
        self._obs_keys: list[str] = []

    def add(self, obs: dict[str, np.ndarray], q: np.ndarray, state: tuple[np.ndarray, np.ndarray],
            actions: np.ndarray, rewards: np.ndarray, next_obs: dict[str, np.ndarray],
            terminated: np.ndarray, truncated: np.ndarray, final_q_fn: FinalQFn) -> SequenceBlock | None:
        """Record step t of every env: ``obs`` s_t (flat arrays [E, ...]) acted on with Q values
        ``q`` float[E, A] from recurrent state ``state`` = (h, c) float[E, H] (zero at an
        episode's first step); ``actions`` int[E]; ``rewards`` float[E]; ``next_obs`` s_{t+1}
        (only the final observations of envs whose episode ended are read);
        ``terminated``/``truncated`` bool[E]."""
        if self.frames is not None:  # one id (or k) per env names the frame of every table
            self._obs_keys = list(obs)
            obs = {FRAME_IDS: np.stack([self.frames.ids(e, obs) for e in range(self.E)])}
        fields = {**{"o:" + k: v for k, v in obs.items()}, "q": np.asarray(q, np.float32),
                  "h": state[0], "c": state[1], "action": actions, "reward": rewards,
                  "terminated": terminated, "truncated": truncated}
        if self._ring is None:
            self._ring = {k: np.zeros((self.W,) + np.shape(v), np.asarray(v).dtype) for k, v in fields.items()}
            self._final = {k: np.zeros_like(v) for k, v in self._ring.items() if k == "q" or k.startswith("o:")}
        row = self.t % self.W
        for k, v in fields.items():
            self._ring[k][row] = v
        ep, P, m = self.ep, self.P, self.m
        done = terminated | truncated
        if done.any():
            idx = done.nonzero()[0]
            if self.frames is not None:
                self._final["o:" + FRAME_IDS][row, idx] = [self.frames.ids(e, next_obs) for e in idx.tolist()]
            else:
                for k, v in next_obs.items():
                    self._final["o:" + k][row, idx] = v[idx]
            self._final["q"][row, idx] = 0.0                 # terminated: nothing to bootstrap
            tr = (truncated & ~terminated).nonzero()[0]   # both set: the episode terminated
            if tr.size:
                self._final["q"][row, tr] = final_q_fn(tr)
        full = (ep >= m) & ((ep - m) % P == 0)               # [ep-m, ep) is complete, s_m = s_t
        s1 = ep // P * P
        s0 = np.where(s1 >= P, s1 - P, s1)                   # the sequence an episode end closes
        if full.any() or done.any():
            env = np.concatenate([full.nonzero()[0], done.nonzero()[0]])
            start = np.concatenate([ep[full] - m, s0[done]])
            ended = np.arange(env.size) >= int(full.sum())
            length = np.where(ended, ep[env] - start + 1, m)
            self._pending.append((env, start, length, ended, self.t - (ep[env] - start)))
        self.ep = np.where(done, 0, ep + 1)
        self.t += 1
        return self.flush() if self.t % self.K == 0 else None

    def flush(self) -> SequenceBlock | None:
        """The sequences closed since the last block (e.g. at shutdown), or None."""
        if not self._pending:
            return None
        env, start, length, ended, t0 = (np.concatenate(a) for a in zip(*self._pending))
        self._pending = []
        block = self._gather(env, start, length, ended, t0)
        if self.frames is not None:
            block.frames, block.frame_base = self.frames.take()
        return block

    def _gather(self, env: np.ndarray, start: np.ndarray, length: np.ndarray, ended: np.ndarray,
                t0: np.ndarray) -> SequenceBlock:
        m = self.m
        pos = np.arange(m + 1)
        rows = (t0[:, None] + pos) % self.W                                   # [S, m+1]
        obs_mask = pos <= length[:, None]                                     # [S, m+1]
        step_mask = pos[:m] < length[:, None]                                 # [S, m]
        e_end, l_end = env[ended], length[ended]
        end_row = rows[ended, l_end - 1]
        data: dict[str, np.ndarray] = {}
        for k, v in self._ring.items():
            if k in ("h", "c"):
                data[k] = v[rows[:, 0], env]
            elif k.startswith("o:") or k == "q":
                g = v[rows, env[:, None]]
                g[ended, l_end] = self._final[k][end_row, e_end]      # s_len of an ended episode
                if k == "o:" + FRAME_IDS:   # padding names s_len's frames: ones the replay holds
                    g = np.where(obs_mask[:, :, None], g, g[np.arange(len(length)), length][:, None])
                    ids = g if self.frames is not None and self.frames.k else g[..., 0]
                    data.update({key: ids for key in self._obs_keys})
                    continue
                g[~obs_mask] = 0
                data[k[2:] if k != "q" else k] = g
            else:
                g = v[rows[:, :m], env[:, None]]
                g[~step_mask] = 0
                data[k] = g
        q = data.pop("q")
        data["first"] = start == 0
        data["mask"] = step_mask
        data["action"] = data["action"].astype(np.int64)
        data["reward"] = data["reward"].astype(np.float32)
        prio = self._priorities(data, q, length)
        return SequenceBlock(data, q, prio, env, start, length)

    def _priorities(self, data: dict[str, np.ndarray], q: np.ndarray, length: np.ndarray) -> np.ndarray:
        S, m, n, gamma = q.shape[0], self.m, self.n, self.gamma
        t = np.arange(m)
        j = np.clip(length[:, None] - t, 0, n)                                # [S, m]
        padded = np.concatenate([data["reward"].astype(np.float64), np.zeros((S, n))], axis=1)
        ret = sum(gamma ** i * padded[:, i:i + m] for i in range(n))          # zeros past len
        v = q.max(-1).astype(np.float64)        # [S, m+1]; q[len] is zero after a terminal: V = 0
        v_boot = np.take_along_axis(v, t + j, axis=1)
        y = value_rescale(ret + gamma ** j * inverse_value_rescale(v_boot, self.eps), self.eps)
        q_sa = np.take_along_axis(q[:, :m], data["action"][:, :, None], axis=2)[:, :, 0]
        trained = data["mask"] & ((t >= self.burn_in) | data["first"][:, None])
        return mixed_priority(np.abs(q_sa - y), trained, self.eta).astype(np.float32)
