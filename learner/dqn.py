"""Ape-X DQN learning step, with no I/O: double DQN, n-step targets, dueling (in the network),
Huber loss weighted by importance-sampling weights, gradient-norm clipping, target network.

Batch layout (flat names, B rows)::

    obs/*      observation s_j                 action    int64[B]
    reward     float32[B]  n-step discounted sum   n  uint8[B]  steps summed (m <= n_step)
    next_obs/* observation s_{j+m}             terminated bool[B]
    weights    float32[B]  IS weights (from the replay)

With ``learner.guard_imitation`` the batch also gets ``guard_action`` int64[B]: the match env's
guard rule on ``obs/enemy_seen`` (-1 where it does not fire), made with the tensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from zenrl.common.errors import ConfigError, ZenrlError
from zenrl.common.config import LearnerConfig, NetworkConfig
from zenrl.common.guard_rule import GuardRule
from zenrl.common.networks import QNetwork, rename_prefix, to_tensors
from zenrl.common.specs import ArraySpec
from zenrl.learner.guard import UpdateGuard, params_finite


def double_dqn_target(q_next_online: torch.Tensor, q_next_target: torch.Tensor, reward: torch.Tensor,
                      n: torch.Tensor, terminated: torch.Tensor, gamma: float) -> torch.Tensor:
    """y = r + gamma^n * (1 - terminated) * Q_target(s', argmax_a Q_online(s', a)). All [B] / [B, A]."""
    a_star = q_next_online.argmax(dim=1, keepdim=True)
    discount = gamma ** n.float() * (1.0 - terminated.float())
    return reward + discount * q_next_target.gather(1, a_star).squeeze(1)


def dqn_item_losses(q: torch.Tensor, action: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
                    huber_delta: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-item IS-weighted Huber losses. q float[B, A], action int64[B], target/weights float[B].
    Returns (losses float[B], |td| float[B], Q(s, a) float[B])."""
    q_sa = q.gather(1, action.long().unsqueeze(1)).squeeze(1)
    td = target.detach() - q_sa
    per = weights * F.huber_loss(q_sa, target.detach(), reduction="none", delta=huber_delta)
    return per, td.abs().detach(), q_sa.detach()


def dqn_loss(q: torch.Tensor, action: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
             huber_delta: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """IS-weighted Huber loss. q float[B, A], action int64[B], target/weights float[B].
    Returns (loss scalar, |td| float[B], Q(s, a) float[B])."""
    per, td_abs, q_sa = dqn_item_losses(q, action, target, weights, huber_delta)
    return per.mean(), td_abs, q_sa


def large_margin_losses(q: torch.Tensor, expert: torch.Tensor, margin: float) -> torch.Tensor:
    """DQfD's large-margin imitation loss (Hester et al. 2018), per item: ``max_a [Q(s,a) + margin *
    (a != a_E)] - Q(s,a_E)``, 0 where ``expert`` is -1 (no expert action). q float[B, A], expert
    int64[B]; returns float[B], >= 0, zero where a_E's Q value leads every other by ``margin``."""
    has = expert >= 0
    a_e = expert.clamp(min=0).unsqueeze(1)
    bonus = torch.full_like(q, float(margin)).scatter(1, a_e, 0.0)
    j = (q + bonus).max(1).values - q.gather(1, a_e).squeeze(1)
    return torch.where(has, j, torch.zeros_like(j))


def screen_rows(data: Mapping[str, np.ndarray], names: Any, limit: float) -> np.ndarray:
    """bool[B]: the rows of ``data`` with a floating-point value of magnitude above ``limit`` (or
    NaN) in any of the fields ``names`` (arrays [B, ...]); integer fields (images) are bounded."""
    bad: np.ndarray | None = None
    for k in names:
        a = data[k]
        if a.dtype.kind != "f" or a.size == 0 or (float(a.max()) <= limit and float(a.min()) >= -limit):
            continue  # (whole-array reductions: the common case costs two, not one per row)
        m = ~(np.abs(a.reshape(a.shape[0], -1)).max(1) <= limit)
        bad = m if bad is None else bad | m
    n = len(next(iter(data.values())))
    return np.zeros(n, bool) if bad is None else bad


@dataclass
class LossTerms:
    """One batch's loss before the step: ``loss`` scalar (differentiable); ``priorities``
    float[B] (detached); ``metrics()`` the step's extra metrics (called after a step);
    ``bad()`` bool[B]: the items whose own forward values are non-finite or whose TD error
    exceeds ``max_priority`` (called only when the step is refused)."""

    loss: torch.Tensor
    priorities: torch.Tensor
    metrics: Callable[[], dict[str, float]]
    bad: Callable[[], torch.Tensor]
    #: scalar: the largest |TD| (None without a bound on it); read with the loss, it refuses a
    #: step whose loss is finite but huge because of a few items (|TD| above ``max_priority``)
    over: torch.Tensor | None = None
    #: ``keep`` int64[K] -> the terms of those items from the same forward (no second forward);
    #: valid when the items left out have finite forward values (:attr:`finite`); None: the
    #: loss is recomputed on the kept items
    subset: Callable[[torch.Tensor], "LossTerms"] | None = None
    #: bool[B]: the items whose forward values are all finite
    finite: Callable[[], torch.Tensor] | None = None


def index_batch(b: Mapping[str, Any], idx: torch.Tensor) -> dict[str, Any]:
    """The rows ``idx`` (int64[K]) of every tensor in a batch (nested dicts of [B, ...] tensors;
    the bookkeeping entries, named ``_...``, are left out)."""
    return {k: index_batch(v, idx) if isinstance(v, Mapping) else v.index_select(0, idx)
            for k, v in b.items() if not k.startswith("_")}


class DQNLearner:
    """Online and target networks plus optimizer; :meth:`update` is one training step.

    Poisoned items, values an env's bounds allow that the network cannot take: items with an
    observation beyond ``learner.max_abs_obs`` are left out of the batch when it is made
    (:meth:`batch_to_tensors`, on the prefetcher's thread: the forward never sees them). When a
    step's loss is non-finite or an item's |TD| exceeds ``max_priority`` (read with the loss,
    before the backward pass), or its gradient is non-finite, the items to blame are found
    (their own forward values non-finite or |TD| above ``max_priority``; failing that, by
    bisecting the batch on the finiteness of loss and gradient) and the step is made on the
    others: from the same forward pass when the blamed items' values are finite, else by a
    second one on the others. The left-out items' indices are in :attr:`poisoned` for the caller
    to report (the replay then never samples them again). A batch whose every item is to blame
    is the learner's problem, not the batch's: skipped by the guard, nothing reported.
    """

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, net_cfg: NetworkConfig,
                 cfg: LearnerConfig, device: torch.device,
                 network: Callable[[Mapping[str, ArraySpec], int, NetworkConfig], nn.Module] = QNetwork,
                 max_priority: float = math.inf, guard: GuardRule | None = None) -> None:
        """``network(obs_spec, n_actions, net_cfg)`` builds the online and the target network
        (R2D2 gives its recurrent one). ``max_priority`` (``replay.max_priority``, above which
        the replay refuses priority updates): an item whose |TD| exceeds it is left out of the
        step and reported, so no priority returned exceeds it. ``guard``: the match env's guard
        rule, for ``cfg.guard_imitation`` (needed when it is on; read on ``obs/enemy_seen``)."""
        if cfg.guard_imitation and (guard is None or "obs/enemy_seen" not in spec):
            raise ConfigError("learner.guard_imitation needs a match env (zenrl/BurgerWar-v0) with enemy_detector: "
                             "true, a discrete action set and dict observations (flatten_obs: false)")
        self.guard_rule = guard if cfg.guard_imitation else None
        self.cfg = cfg
        self.device = device
        self.max_priority = float(max_priority)
        self.obs_spec = {k: v for k, v in spec.items() if k == "obs" or k.startswith("obs/")}
        self.online = network(self.obs_spec, n_actions, net_cfg).to(device)
        self.target = network(self.obs_spec, n_actions, net_cfg).to(device)
        self.target.load_state_dict(self.online.state_dict())
        self.target.requires_grad_(False)
        self._fused = cfg.optimizer == "adam" and device.type in ("cpu", "cuda")
        if cfg.optimizer == "adam":
            # the fused kernel: one op per step instead of a dozen, the same arithmetic
            self.opt: torch.optim.Optimizer = torch.optim.Adam(self.online.parameters(), lr=cfg.lr, eps=cfg.adam_eps,
                                                               fused=self._fused)
        else:
            self.opt = torch.optim.RMSprop(self.online.parameters(), lr=cfg.lr, alpha=0.95, eps=0.01, centered=True)
        self.n_actions = int(n_actions)
        self.updates = 0
        self.guard = UpdateGuard(cfg.guard_max_bad_updates, cfg.guard_log_interval_s)
        #: indices (int64[P]) into the last batch of :meth:`update` of the items found poisonous
        self.poisoned = np.zeros(0, np.int64)
        self.poisoned_total = 0  #: items found poisonous so far
        self.repaired_updates = 0  #: steps made without the poisonous items of their batch

    def beta(self) -> float:
        frac = min(1.0, self.updates / self.cfg.beta_anneal_updates)
        return self.cfg.beta0 + frac * (1.0 - self.cfg.beta0)

    def check_actions(self, a: np.ndarray) -> None:
        """ValueError for an action index the network does not have (``gather`` would crash the
        step, or assert on CUDA and poison the context)."""
        if a.size and (int(a.min()) < 0 or int(a.max()) >= self.n_actions):
            raise ValueError(f"batch has action {int(a.max()) if int(a.max()) >= self.n_actions else int(a.min())} "
                             f"outside 0..{self.n_actions - 1}")

    def screen(self, data: Mapping[str, np.ndarray], weights: np.ndarray,
               fields: Any) -> tuple[Mapping[str, np.ndarray], np.ndarray, dict[str, Any]]:
        """Leave out the rows with an observation (``fields``) beyond ``max_abs_obs``: returns
        (data, weights, bookkeeping) where the bookkeeping entries name the rows kept (``_rows``
        int64[K] or None when all are) and left out (``_screened`` int64[P]) and the batch size
        (``_n``)."""
        n = len(weights)
        bad = screen_rows(data, fields, self.cfg.max_abs_obs)
        if not bad.any():
            return data, weights, {"_rows": None, "_screened": np.zeros(0, np.int64), "_n": n}
        rows = np.flatnonzero(~bad)
        return ({k: v[rows] for k, v in data.items()}, np.asarray(weights)[rows],
                {"_rows": rows, "_screened": np.flatnonzero(bad), "_n": n})

    def batch_to_tensors(self, data: Mapping[str, np.ndarray], weights: np.ndarray) -> dict[str, Any]:
        """Tensors for :meth:`update` (:meth:`check_actions` first, then :meth:`screen`)."""
        self.check_actions(data["action"])
        data, weights, book = self.screen(data, weights, [k for k in data if k.startswith(("obs", "next_obs"))])
        t = to_tensors({k: v for k, v in data.items() if k in ("action", "reward", "n", "terminated")}, self.device)
        t["obs"] = to_tensors({k: data[k] for k in self.obs_spec}, self.device)
        t["next_obs"] = to_tensors(rename_prefix(data, "next_obs", "obs"), self.device)
        t["weights"] = torch.from_numpy(np.array(weights, np.float32)).to(self.device)
        if self.guard_rule is not None:
            t["guard_action"] = torch.from_numpy(self.guard_rule.actions(data["obs/enemy_seen"])).to(self.device)
        t.update(book)
        return t

    def loss_terms(self, b: Mapping[str, Any]) -> LossTerms:
        """Double-DQN n-step loss of a batch from :meth:`batch_to_tensors`."""
        with torch.no_grad():
            q_next_online = self.online(b["next_obs"])
            q_next_target = self.target(b["next_obs"])
            y = double_dqn_target(q_next_online, q_next_target, b["reward"].float(), b["n"], b["terminated"], self.cfg.gamma)
        q = self.online(b["obs"])
        per, td_abs, q_sa = dqn_item_losses(q, b["action"], y, b["weights"], self.cfg.huber_delta)
        imitation = None
        if "guard_action" in b:
            imitation = large_margin_losses(q, b["guard_action"], self.cfg.guard_margin)
            per = per + self.cfg.guard_imitation * imitation

        def metrics(keep: torch.Tensor | None = None) -> dict[str, float]:
            qs = q_sa if keep is None else q_sa.index_select(0, keep)
            out = {"q_mean": float(qs.mean().item())}
            if imitation is not None:
                fired = b["guard_action"] >= 0
                if keep is not None:
                    fired, im = fired.index_select(0, keep), imitation.index_select(0, keep)
                else:
                    im = imitation
                n = int(fired.sum().item())
                out["guard_fired"] = n / max(1, fired.numel())
                out["guard_margin_loss"] = float(im.sum().item()) / n if n else 0.0
            return out

        def finite() -> torch.Tensor:
            with torch.no_grad():
                return (torch.isfinite(q).all(1) & torch.isfinite(q_next_online).all(1)
                        & torch.isfinite(q_next_target).all(1) & torch.isfinite(y))

        def bad() -> torch.Tensor:
            return ~finite() | ~(td_abs <= self.max_priority)  # NaN |td| is blamed too

        def subset(keep: torch.Tensor) -> LossTerms:
            return LossTerms(per.index_select(0, keep).mean(), td_abs.index_select(0, keep),
                             lambda: metrics(keep), bad)

        return LossTerms(per.mean(), td_abs, metrics, bad, self._over(td_abs), subset, finite)

    def _over(self, abs_td: torch.Tensor) -> torch.Tensor | None:
        """The largest entry of ``abs_td`` (any shape), or None without a bound to compare it to."""
        return None if math.isinf(self.max_priority) or abs_td.numel() == 0 else abs_td.max()

    def update(self, b: Mapping[str, Any]) -> tuple[dict[str, float], np.ndarray | None]:
        """:meth:`step_on` the batch, counting the items left out."""
        out = self.step_on(b)
        self.poisoned_total += self.poisoned.shape[0]
        return out

    def step_on(self, b: Mapping[str, Any]) -> tuple[dict[str, float], np.ndarray | None]:
        """One step on a batch (from :meth:`batch_to_tensors`); returns (metrics, new priorities
        float32[B], none above ``max_priority``). Items found poisonous are left out of the step,
        their indices in :attr:`poisoned` and their priorities 0 (not to be sent). A step that
        cannot be made finite is skipped (see :attr:`guard`): metrics are then empty and
        priorities ``None`` (:attr:`poisoned` may still name items)."""
        rows, screened = b.get("_rows"), b.get("_screened", np.zeros(0, np.int64))
        self.poisoned = screened
        t = self.loss_terms(b)
        loss_v, top = self._read(t.loss, t.over)
        norm_v = math.nan
        reuse = t.subset is not None and t.finite is not None  # the forward's graph is still there
        if math.isfinite(loss_v) and top <= self.max_priority:
            norm_v = self._backward(t.loss)
            if math.isfinite(norm_v):
                self.guard.accept(loss_v, norm_v)  # resets the run of skipped steps
                return self._finish(b, t, loss_v, norm_v, None)
            self.opt.zero_grad(set_to_none=True)
            reuse = False  # the backward pass freed it
            bad = np.zeros(len(t.priorities), bool)
            bad[self._culprits(b, np.arange(bad.shape[0]))] = True
        else:
            bad = t.bad().cpu().numpy()
            if not bad.any():
                bad[self._culprits(b, np.arange(bad.shape[0]))] = True
        if bad.all() or not bad.any():  # nothing to blame, or everything: the learner's problem
            self.guard.accept(loss_v, norm_v)
            return {}, None
        blamed = np.flatnonzero(bad)
        self.poisoned = np.sort(np.concatenate([screened, blamed if rows is None else rows[blamed]]))
        keep = torch.from_numpy(np.flatnonzero(~bad)).to(self.device)
        if reuse and bool(t.finite()[torch.from_numpy(blamed).to(self.device)].all()):
            t2 = t.subset(keep)  # the same forward pass: the blamed items' gradients are exact zeros
        else:
            t2 = self.loss_terms(index_batch(b, keep))
        loss_v, _ = self._read(t2.loss)
        norm_v = self._backward(t2.loss)
        if not self.guard.accept(loss_v, norm_v):
            self.opt.zero_grad(set_to_none=True)
            return {}, None
        self.repaired_updates += 1
        return self._finish(b, t2, loss_v, norm_v, keep)

    def _read(self, loss: torch.Tensor, over: torch.Tensor | None = None) -> tuple[float, float]:
        """(loss, ``over`` or 0), read in one device sync before the backward pass."""
        if over is None:
            return float(loss.item()), 0.0
        v = torch.stack([loss.detach(), over.to(loss.dtype)]).tolist()
        return v[0], v[1]

    def _backward(self, loss: torch.Tensor) -> float:
        """Gradients of ``loss`` (clipped to ``grad_clip``); returns the pre-clip gradient norm."""
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        return float(nn.utils.clip_grad_norm_(self.online.parameters(), self.cfg.grad_clip).item())

    def _finish(self, b: Mapping[str, Any], t: LossTerms, loss_v: float, norm_v: float,
                keep: torch.Tensor | None) -> tuple[dict[str, float], np.ndarray]:
        """Step, and the priorities of the whole batch as sampled (0 where left out)."""
        self._step()
        # each kept |TD| is <= max_priority (a larger one is blamed), or the guard has no bound
        prios = t.priorities.cpu().numpy().astype(np.float32)
        rows = b.get("_rows")
        if keep is not None:
            rows = keep.cpu().numpy() if rows is None else rows[keep.cpu().numpy()]
        if rows is not None:
            full = np.zeros(b["_n"], np.float32)
            full[rows] = prios
            prios = full
        return {"loss": loss_v, "grad_norm": norm_v, **t.metrics()}, prios

    def _culprits(self, b: Mapping[str, Any], idx: np.ndarray) -> np.ndarray:
        """Within ``idx`` (a set of items whose step is non-finite), the single items whose own
        loss or gradient is non-finite, by bisection (O(k log B) small steps for k of them);
        none when only a combination is (then nobody is blamed)."""
        if idx.shape[0] == 1:
            return idx
        found = [self._culprits(b, h) for h in (idx[: idx.shape[0] // 2], idx[idx.shape[0] // 2:])
                 if not self._finite_on(b, h)]
        return np.concatenate(found) if found else np.zeros(0, np.int64)

    def _finite_on(self, b: Mapping[str, Any], idx: np.ndarray) -> bool:
        loss = self.loss_terms(index_batch(b, torch.from_numpy(idx).to(self.device))).loss
        norm_v = self._backward(loss)
        self.opt.zero_grad(set_to_none=True)
        return math.isfinite(float(loss.item())) and math.isfinite(norm_v)

    def _step(self) -> None:
        self.opt.step()
        self.updates += 1
        if self.updates % self.cfg.target_update_period == 0:
            self.target.load_state_dict(self.online.state_dict())

    def optimize(self, loss: torch.Tensor) -> tuple[float, float] | None:
        """One optimizer step on ``loss`` behind the guard (gradients clipped to
        ``grad_clip``), the target copied every ``target_update_period`` updates. Returns
        (loss, gradient norm), or None when the guard skipped the step."""
        norm_v = self._backward(loss)
        loss_v = float(loss.item())
        if not self.guard.accept(loss_v, norm_v):
            self.opt.zero_grad(set_to_none=True)
            return None
        self._step()
        return loss_v, norm_v

    def values(self) -> dict[str, int]:
        """The guard's counters plus ``poisoned_items`` and ``repaired_updates``."""
        return {**self.guard.values(), "poisoned_items": self.poisoned_total, "repaired_updates": self.repaired_updates}

    def params_finite(self) -> bool:
        """Whether the online and target networks are finite (checked before publish or save)."""
        return params_finite(self.online.parameters()) and params_finite(self.target.parameters())

    # -- training state ----------------------------------------------------------------------
    def load_initial(self, weights: Mapping[str, Any], source: str) -> None:
        """Start from ``weights`` (a Q-network ``state_dict``, ``learner.init_from``): online and
        target alike, the optimizer fresh. A :class:`ZenrlError` names ``source`` if the shapes or
        names differ from this network's."""
        try:
            self.online.load_state_dict(weights)
        except (RuntimeError, KeyError) as e:
            first = str(e).strip().splitlines()
            raise ZenrlError(f"learner.init_from {source!r} does not fit this network ({type(self.online).__name__}): "
                             f"{first[1].strip() if len(first) > 1 else first[0]}") from None
        self.target.load_state_dict(self.online.state_dict())

    def state_dict(self) -> dict[str, Any]:
        return {"online": self.online.state_dict(), "target": self.target.state_dict(),
                "optimizer": self.opt.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.online.load_state_dict(state["online"])
        self.target.load_state_dict(state["target"])
        self.opt.load_state_dict(state["optimizer"])
        if self._fused:
            # saved groups carry the writer's flags (None from an unfused Adam): fuse here, with
            # the step counters where the fused kernel wants them (float32, on the parameter's device)
            for group in self.opt.param_groups:
                group["fused"], group["foreach"] = True, None
                for p in group["params"]:
                    st = self.opt.state.get(p)
                    if st and "step" in st:
                        st["step"] = st["step"].to(p.device, torch.float32)
        self.updates = int(state["updates"])
