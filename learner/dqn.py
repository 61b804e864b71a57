"""Ape-X DQN learning step, with no I/O: double DQN, n-step targets, dueling (in the network),
Huber loss weighted by importance-sampling weights, gradient-norm clipping, target network.

Batch layout (flat names, B rows)::

    obs/*      observation s_j                 action    int64[B]
    reward     float32[B]  n-step discounted sum   n  uint8[B]  steps summed (m <= n_step)
    next_obs/* observation s_{j+m}             terminated bool[B]
    weights    float32[B]  IS weights (from the replay)
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from zenrl.common.config import LearnerConfig, NetworkConfig
from zenrl.common.networks import QNetwork, rename_prefix, to_tensors
from zenrl.common.specs import ArraySpec
from zenrl.learner.guard import UpdateGuard, params_finite


def double_dqn_target(q_next_online: torch.Tensor, q_next_target: torch.Tensor, reward: torch.Tensor,
                      n: torch.Tensor, terminated: torch.Tensor, gamma: float) -> torch.Tensor:
    """y = r + gamma^n * (1 - terminated) * Q_target(s', argmax_a Q_online(s', a)). All [B] / [B, A]."""
    a_star = q_next_online.argmax(dim=1, keepdim=True)
    discount = gamma ** n.float() * (1.0 - terminated.float())
    return reward + discount * q_next_target.gather(1, a_star).squeeze(1)


def dqn_loss(q: torch.Tensor, action: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
             huber_delta: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """IS-weighted Huber loss. q float[B, A], action int64[B], target/weights float[B].
    Returns (loss scalar, |td| float[B], Q(s, a) float[B])."""
    q_sa = q.gather(1, action.long().unsqueeze(1)).squeeze(1)
    td = target.detach() - q_sa
    loss = (weights * F.huber_loss(q_sa, target.detach(), reduction="none", delta=huber_delta)).mean()
    return loss, td.abs().detach(), q_sa.detach()


class DQNLearner:
    """Online and target networks plus optimizer; :meth:`update` is one training step."""

    def __init__(self, spec: Mapping[str, ArraySpec], n_actions: int, net_cfg: NetworkConfig,
                 cfg: LearnerConfig, device: torch.device,
                 network: Callable[[Mapping[str, ArraySpec], int, NetworkConfig], nn.Module] = QNetwork) -> None:
        """``network(obs_spec, n_actions, net_cfg)`` builds the online and the target network
        (R2D2 gives its recurrent one)."""
        self.cfg = cfg
        self.device = device
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

    def beta(self) -> float:
        frac = min(1.0, self.updates / self.cfg.beta_anneal_updates)
        return self.cfg.beta0 + frac * (1.0 - self.cfg.beta0)

    def check_actions(self, a: np.ndarray) -> None:
        """ValueError for an action index the network does not have (``gather`` would crash the
        step, or assert on CUDA and poison the context)."""
        if a.size and (int(a.min()) < 0 or int(a.max()) >= self.n_actions):
            raise ValueError(f"batch has action {int(a.max()) if int(a.max()) >= self.n_actions else int(a.min())} "
                             f"outside 0..{self.n_actions - 1}")

    def batch_to_tensors(self, data: Mapping[str, np.ndarray], weights: np.ndarray) -> dict[str, Any]:
        """Tensors for :meth:`update` (:meth:`check_actions` first)."""
        self.check_actions(data["action"])
        t = to_tensors({k: v for k, v in data.items() if k in ("action", "reward", "n", "terminated")}, self.device)
        t["obs"] = to_tensors({k: data[k] for k in self.obs_spec}, self.device)
        t["next_obs"] = to_tensors(rename_prefix(data, "next_obs", "obs"), self.device)
        t["weights"] = torch.from_numpy(np.array(weights, np.float32)).to(self.device)
        return t

    def update(self, b: Mapping[str, Any]) -> tuple[dict[str, float], np.ndarray | None]:
        """One step on a batch from :meth:`batch_to_tensors`; returns (metrics, new priorities
        float32[B] = |td|). A non-finite loss or gradient skips the step (see :attr:`guard`):
        metrics are then empty and priorities ``None``."""
        with torch.no_grad():
            q_next_online = self.online(b["next_obs"])
            q_next_target = self.target(b["next_obs"])
            y = double_dqn_target(q_next_online, q_next_target, b["reward"].float(), b["n"], b["terminated"], self.cfg.gamma)
        q = self.online(b["obs"])
        loss, td_abs, q_sa = dqn_loss(q, b["action"], y, b["weights"], self.cfg.huber_delta)
        stepped = self.optimize(loss)
        if stepped is None:
            return {}, None
        loss_v, norm_v = stepped
        metrics = {"loss": loss_v, "q_mean": float(q_sa.mean().item()), "grad_norm": norm_v}
        return metrics, td_abs.cpu().numpy().astype(np.float32)

    def optimize(self, loss: torch.Tensor) -> tuple[float, float] | None:
        """One optimizer step on ``loss`` behind the guard (gradients clipped to
        ``grad_clip``), the target copied every ``target_update_period`` updates. Returns
        (loss, gradient norm), or None when the guard skipped the step."""
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.online.parameters(), self.cfg.grad_clip)
        # the metrics' .item() calls, made before the step: the guard costs no extra device sync
        loss_v, norm_v = float(loss.item()), float(grad_norm.item())
        if not self.guard.accept(loss_v, norm_v):
            self.opt.zero_grad(set_to_none=True)
            return None
        self.opt.step()
        self.updates += 1
        if self.updates % self.cfg.target_update_period == 0:
            self.target.load_state_dict(self.online.state_dict())
        return loss_v, norm_v

    def params_finite(self) -> bool:
        """Whether the online and target networks are finite (checked before publish or save)."""
        return params_finite(self.online.parameters()) and params_finite(self.target.parameters())

    # -- training state ----------------------------------------------------------------------
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
