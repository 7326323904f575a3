"""What the agent learns from, and the batches drawn from it (docs/design.md, "Learning").

``Experience`` holds the agent's own replay (uniform or proportional prioritized) and the
demonstrations of the neutral rule-based driver; an update's batch takes a share from each
and scores every transition's reward vector under mode weights: the run's mode, or for a
mode-conditioned network weights drawn afresh per transition by ``WeightSampler`` from the
configured modes and the simplex around them (relabelling, as in conditioned multi-objective
Q-learning). Each CAV row learns from its own credit or, as an ablation, the global reward.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from exit_decision.config import PrioritizedReplayConfig, ProjectConfig, TrainingConfig
from exit_decision.learning.replay import PrioritizedSampler, ReplayBuffer, Transition, scored_rewards
from exit_decision.reward import weight_input, weights_of_input


class WeightSampler:
    """Mode weights for relabelling: one of the configured modes exactly, or a point of the
    simplex near one (Dirichlet around its decision weights, Beta around its incentive)."""

    def __init__(self, config: ProjectConfig, modes: list[str], exact_share: float, concentration: float,
                 rng: np.random.Generator):
        self.anchors = np.array([weight_input(config.mode(m)) for m in modes])
        self.exact_share, self.concentration, self.rng = exact_share, concentration, rng

    def sample(self, count: int) -> np.ndarray:
        anchors = self.anchors[self.rng.integers(len(self.anchors), size=count)]
        near = self.rng.random(count) >= self.exact_share
        if near.any():
            concentrated = self.concentration * anchors[near] + 1e-3
            decision = dirichlet_rows(self.rng, concentrated[:, :4])
            incentive = self.rng.beta(concentrated[:, 4], concentrated[:, 5])
            anchors[near] = np.column_stack([decision, incentive, 1.0 - incentive])
        return anchors


def dirichlet_rows(rng: np.random.Generator, alpha: np.ndarray) -> np.ndarray:
    """One Dirichlet draw per row of ``alpha`` (M, K), by stick breaking: component j is a
    Beta(alpha_j, alpha_j+1 + ... + alpha_K) share of what the components before it left (the
    same distribution as ``rng.dirichlet``, which takes one alpha at a time)."""
    tails = alpha[:, ::-1].cumsum(axis=1)[:, ::-1]   # alpha_j + ... + alpha_K
    draws = np.empty_like(alpha)
    left = np.ones(len(alpha))
    for j in range(alpha.shape[1] - 1):
        share = rng.beta(alpha[:, j], tails[:, j + 1])
        draws[:, j] = left * share
        left = left * (1.0 - share)
    draws[:, -1] = left
    return draws


@dataclass(frozen=True)
class SampledBatch:
    """One update's batch: the arrays the agent learns from, which rows are demonstrations,
    the importance weights (prioritized replay; None: uniform) and the replay indices drawn."""
    arrays: dict[str, np.ndarray]
    is_demo: np.ndarray
    importance: np.ndarray | None
    indices: np.ndarray


class Experience:
    """The agent's replay and the demonstrations, for graphs of ``rows`` rows, ``features``
    features and ``actions`` actions. ``weights``: the conditioned network's relabelling
    (None: every transition is scored under ``learning_weights``, the run's mode in the
    learning reward; a baseline's reward has no modes)."""

    def __init__(self, training: TrainingConfig, prioritized: PrioritizedReplayConfig | None, rows: int,
                 features: int, actions: int, weights: WeightSampler | None, learning_weights: np.ndarray,
                 rng: np.random.Generator):
        self.training, self.weights, self.learning_weights, self.rng = training, weights, learning_weights, rng
        self.replay = ReplayBuffer(training.replay_size, rows, features, actions)
        self.priorities = PrioritizedSampler(training.replay_size, prioritized.alpha, prioritized.beta) \
            if prioritized else None
        self.demos = ReplayBuffer(max(1, 250 * training.demonstrations.episodes), rows, features, actions)
        #: ``bootstrap: prior``: the prior's option at each transition's weight multipliers
        #: ((B, 4, 2) -> (B,)), given to the batch as ``prior_actions``; set once the prior is measured
        self.prior_actions: Callable[[np.ndarray], np.ndarray] | None = None

    def add(self, transition: Transition) -> None:
        """The agent's own transition (prioritized replay: at the highest priority so far)."""
        index = self.replay.add(transition)
        if self.priorities is not None:
            self.priorities.added(index)

    def sample(self) -> SampledBatch:
        """A batch from the agent's replay and the demonstrations (all demonstrations while the
        replay is empty), each transition scored under mode weights."""
        t = self.training
        demo_count = 0
        if len(self.demos):
            demo_count = round(t.batch_size * t.demonstrations.batch_share) if len(self.replay) else t.batch_size
        own_count = t.batch_size - demo_count
        parts, is_demo = [], []
        indices, importance = np.zeros(0, np.int64), np.ones(demo_count, np.float32)
        if own_count:
            if self.priorities is not None:
                indices, own_importance = self.priorities.sample(own_count, self.rng)
                importance = np.concatenate([own_importance, importance])
            else:
                indices = self.rng.integers(len(self.replay), size=own_count)
            parts.append(self.replay.sample(indices))
            is_demo.append(np.zeros(own_count, bool))
        if demo_count:
            parts.append(self.demos.sample(self.rng.integers(len(self.demos), size=demo_count)))
            is_demo.append(np.ones(demo_count, bool))
        batch = parts[0] if len(parts) == 1 else {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        size = len(batch['discounts'])
        if self.weights is not None:
            weights = self.weights.sample(size)
            batch['weights'] = weights.astype(np.float32)
            multipliers = weights_of_input(weights)
        else:
            multipliers = np.broadcast_to(self.learning_weights, (size, 4, 2))
        batch['rewards'] = scored_rewards(batch, multipliers, t.credit) * np.float32(t.reward_scale)
        if self.prior_actions is not None:
            batch['prior_actions'] = self.prior_actions(multipliers)
        del batch['returns'], batch['global_returns']
        return SampledBatch(batch, np.concatenate(is_demo), importance if self.priorities is not None else None,
                            indices)

    def learned(self, sampled: SampledBatch, errors: np.ndarray) -> None:
        """After an update on ``sampled``: prioritized replay takes its rows' TD errors as priorities."""
        if self.priorities is not None and len(sampled.indices):
            self.priorities.update(sampled.indices, errors[:len(sampled.indices)])
