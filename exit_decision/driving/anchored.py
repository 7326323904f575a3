"""A policy over options anchored on its prior (issue 39): it departs from the prior's option only
where its ensemble is confident that another option is better.

The members (a checkpoint's networks, ``model.policy.GraphPolicy.members``, one per training seed)
value every option as the prior's continuation would (``training.bootstrap: prior``). At a CAV's
row, option o scores the lower confidence bound of its advantage over the prior's option p:

    score(o) = mean_k A_k(o) - kappa * std_k A_k(o),   A_k(o) = Q_k(o) - Q_k(p),   score(p) = margin

and the greedy choice over the scores (``policy.PolicyDriver``) keeps the prior unless some
option's bound beats ``margin``: where the members disagree the bound falls, and the CAV falls back
to the prior. ``kappa`` 0 and ``margin`` 0 is the greedy choice of the members' mean. The prior's
option is the best constant style at the mode's weights (``prior.PriorTable``), chosen at each mode.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from exit_decision.agents.options import OptionSpace
from exit_decision.driving.prior import PriorTable
from exit_decision.errors import PolicyError
from exit_decision.graph import TrafficGraph
from exit_decision.model.modes import Mode
from exit_decision.model.policy import PolicyController
from exit_decision.traffic import TrafficSnapshot


@dataclass(frozen=True)
class Anchor:
    kappa: float    # the lower bound's width in the members' standard deviations
    margin: float   # what the bound must beat to depart [the learning reward's units]

    def scores(self, q: np.ndarray, prior_option: int) -> np.ndarray:
        """(N, A) the departure scores of the members' (K, N, A) Q values."""
        advantage = q - q[:, :, prior_option:prior_option + 1]
        spread = advantage.std(axis=0, ddof=1) if len(q) > 1 else np.zeros(advantage.shape[1:])
        score = advantage.mean(axis=0) - self.kappa * spread
        score[:, prior_option] = self.margin
        return score

    def to_metadata(self) -> dict:
        return asdict(self)

    @classmethod
    def from_metadata(cls, data: Mapping) -> Anchor:
        return cls(float(data['kappa']), float(data['margin']))


class AnchoredSource:
    """A loaded anchored policy as a policy driver's Q source (``policy.QSource``): its departure
    scores in place of Q values."""

    def __init__(self, controller: PolicyController, space: OptionSpace):
        policy = controller.policy
        if policy.prior is None:
            raise PolicyError(f'{policy.path}: an anchored policy without its prior table')
        self.controller, self.name = controller, controller.name
        self.shield, self.planner = controller.shield, controller.planner
        self.anchor = Anchor.from_metadata(policy.metadata['anchor'])
        self.table = PriorTable.from_metadata(policy.prior)
        self.space = space
        self.prior_option = -1

    def network_weights(self, mode: Mode) -> np.ndarray | None:
        weights = self.controller.network_weights(mode)
        self.prior_option = self.table.best_option(self.space, mode.weights)
        return weights

    def q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot, network_weights: np.ndarray | None) -> np.ndarray:
        q = self.controller.policy.member_q_values(graph, snapshot, network_weights)
        return self.anchor.scores(q, self.prior_option)
