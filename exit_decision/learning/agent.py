"""The Q-learning update every method shares (paper 000 Section 3; docs/design.md, "Learning" and
"The other papers' methods").

Every CAV row is a Q-learner with shared weights. For a row i that acted at t, with R_i the
row's m-step return (its own credit or the shared reward, scored under the batch element's
mode weights w by the trainer) and gamma^K the window's discount:
- single (GQN, DQN):    y_i = R + gamma^K * Q_target(s')_i[a*], a* = argmax allowed Q_target(s')_i
- double (MDGQN, DDQN): y_i = R + gamma^K * Q_target(s')_i[a*], a* = argmax allowed Q_online(s')_i
- over options with ``bootstrap: prior``: a* = the prior's option at the batch element's weights
  (``driving.prior``; SPIBB's bootstrapping to the baseline), so Q is the prior's, and a greedy
  choice on it is one step of policy improvement
(the m of the window is the method's: 1 for GQN, 3 for MDGQN). Over options, a row whose option
is still held at s' bootstraps on Q(s')_i[a_i], the option it holds (intra-option learning). With prioritized replay each
transition's loss is weighted by its importance weight and its new priority is the largest
|TD error| of its rows. A
mode-conditioned network evaluates every Q at the same w the reward was scored with. A row whose
vehicle left (or the episode ended) has no bootstrap. Demonstration rows add DQfD's
large-margin loss max_a [Q(s,a) + l(a, a_E)] - Q(s, a_E) over the allowed actions.
Target networks follow by soft update: theta- <- tau theta + (1 - tau) theta-.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
import numpy as np
import torch
from torch import nn

from exit_decision.model.networks import GraphQNetwork, NetworkShape, SelectedRows

@dataclass(frozen=True)
class UpdateSettings:
    double: bool           # choose the bootstrap action with the online network (double Q-learning)
    learning_rate: float
    tau: float
    margin: float          # l(a, a_E) for a != a_E
    gradient_clip: float


class GraphQAgent:
    def __init__(self, shape: NetworkShape, settings: UpdateSettings, seed: int):
        torch.manual_seed(seed)
        self.settings = settings
        self.online = GraphQNetwork(shape)
        self.target = copy.deepcopy(self.online).requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=settings.learning_rate, fused=True)   # one kernel

    def set_learning_rate(self, learning_rate: float) -> None:
        for group in self.optimizer.param_groups:
            group['lr'] = learning_rate

    def soft_update(self) -> None:
        tau = self.settings.tau
        with torch.no_grad():   # target <- (1 - tau) target + tau online, every tensor in one call
            torch._foreach_lerp_(list(self.target.parameters()), list(self.online.parameters()), tau)

    @staticmethod
    def masked_argmax(q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return q.masked_fill(~mask, -torch.inf).argmax(-1)

    def td_targets(self, batch: dict[str, torch.Tensor], rows: torch.Tensor) -> torch.Tensor:
        b = rows[:, 0]
        next_rows = SelectedRows.of(batch['next_adjacency'], rows, batch.get('next_degrees'))
        next_mask = next_rows.at(batch['next_masks'])
        alive = next_rows.at(batch['alive']) & next_mask.any(-1)
        weights = batch.get('weights')
        target_q = self.target.cav_q_values(batch['next_features'], next_rows, weights)
        if 'prior_actions' in batch:   # bootstrap on the prior's option (its route option: always allowed)
            best = batch['prior_actions'].index_select(0, b)
        else:
            chooser = self.online.cav_q_values(batch['next_features'], next_rows, weights) \
                if self.settings.double else target_q
            best = self.masked_argmax(chooser, next_mask)
        if 'continuing' in batch:   # options: a row whose option goes on is valued by that option
            best = torch.where(next_rows.at(batch['continuing']), next_rows.at(batch['actions']), best)
        bootstrap = target_q.gather(1, best.unsqueeze(1)).squeeze(1)
        bootstrap = torch.where(alive, bootstrap, torch.zeros_like(bootstrap))
        return next_rows.at(batch['rewards']) + batch['discounts'].index_select(0, b) * bootstrap

    def losses(self, batch: dict[str, torch.Tensor], demo: torch.Tensor,
               sample_weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(TD loss, margin loss, |TD error| per batch element): means over the acting rows
        (TD: weighted by their transition's importance weight; margin: demonstration rows only)."""
        rows = torch.nonzero(batch['actions'] >= 0)
        b = rows[:, 0]
        selected = SelectedRows.of(batch['adjacency'], rows, batch.get('degrees'))
        actions = selected.at(batch['actions'])
        q = self.online.cav_q_values(batch['features'], selected, batch.get('weights'))
        q_taken = q.gather(1, actions.unsqueeze(1)).squeeze(1)
        with torch.no_grad():
            targets = self.td_targets(batch, rows)
        per_row = nn.functional.smooth_l1_loss(q_taken, targets, reduction='none')
        td = (per_row * sample_weights.index_select(0, b)).mean() if sample_weights is not None else per_row.mean()
        errors = torch.zeros(len(demo), dtype=q.dtype).scatter_reduce_(
            0, b, (q_taken - targets).abs().detach(), 'amax', include_self=False)
        demo_rows = demo[b]
        if not demo_rows.any():
            return td, torch.zeros((), dtype=td.dtype), errors
        margins = torch.full_like(q, self.settings.margin)
        margins.scatter_(1, actions.unsqueeze(1), 0.0)
        allowed = selected.at(batch['masks'])
        best = (q + margins).masked_fill(~allowed, -torch.inf).max(1).values
        margin_loss = (best - q_taken)[demo_rows].mean()
        return td, margin_loss, errors

    def update(self, batch: dict[str, np.ndarray], demo: np.ndarray, margin_weight: float,
               sample_weights: np.ndarray | None = None) -> tuple[dict[str, float], np.ndarray]:
        """One gradient step; (losses, |TD error| per batch element for the priorities)."""
        tensors = {key: torch.from_numpy(value) for key, value in batch.items()}
        td, margin, errors = self.losses(tensors, torch.from_numpy(demo),
                                         None if sample_weights is None else torch.from_numpy(sample_weights))
        loss = td + margin_weight * margin
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.online.parameters(), self.settings.gradient_clip)
        self.optimizer.step()
        self.soft_update()
        return {'loss': loss.item(), 'td_loss': td.item(), 'margin_loss': margin.item()}, errors.numpy()
