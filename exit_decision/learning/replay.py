"""Replay of m-step transitions between decisions, built so that windows never cross an episode.

``EpisodeAccumulator`` collects an episode's decisions (graph, actions, masks, reward
vectors) and emits, for decision t, the transition to t + K with K = min(m, decisions left):
returns R = sum_k gamma^k r_{t+k} as *reward vectors* (4 rows x [incentive, punishment],
``exit_decision.reward``), so a sampled transition can be scored under any mode; the
bootstrap discount gamma^K, or 0 when the episode terminated inside the window; and per row
whether the same vehicle is still in that row at t + K (a CAV that left or collided gets a
terminal target). With options (``DecisionRecord.choosing``), every CAV row acts at every
decision with the option it holds, and a row whose option is still held at t + K bootstraps on
that option's value instead of the best one (intra-option Q-learning, Sutton, Precup and Singh
1999: the option's value is discounted by the time it is held). Two returns are kept: each acting row's own credit (its own terms plus an
equal share of the terms no CAV owns, summed only while the same vehicle holds the row) and
the episode's global vector (the paper's shared reward, for the ablation).
``ReplayBuffer`` stores them in flat arrays (masks and adjacency bit-packed) and samples
batches; demonstrations live in their own buffer that is never overwritten.
``PrioritizedSampler`` draws a buffer's indices in proportion to their priorities
(paper 003's prioritized replay); otherwise indices are drawn uniformly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from exit_decision.actions import NO_ACTION
from exit_decision.graph import TrafficGraph
from exit_decision.reward import credit


@dataclass(frozen=True)
class DecisionRecord:
    graph: TrafficGraph
    actions: np.ndarray      # (N,) int, NO_ACTION on rows that did not act
    masks: np.ndarray        # (N, A) bool, the masks the actions were chosen under
    own: np.ndarray | None = None      # (N, 4, 2) each acting row's own reward vector until the next decision
    shared: np.ndarray | None = None   # (4, 2) the terms no acting row owns
    choosing: np.ndarray | None = None  # (N,) bool, options: the rows that began their option here (None: grid)

    def credit(self) -> np.ndarray:
        """(N, 4, 2): each acting row's own terms plus an equal share of the shared ones."""
        return credit(self.own, self.shared, self.actions >= 0)

    def total(self) -> np.ndarray:
        return self.own.sum(0) + self.shared


@dataclass(frozen=True)
class Transition:
    features: np.ndarray
    adjacency: np.ndarray
    actions: np.ndarray
    masks: np.ndarray
    returns: np.ndarray      # (N, 4, 2) per-row credit, m-step discounted
    global_return: np.ndarray  # (4, 2) the shared reward vector, m-step discounted
    discount: float
    alive: np.ndarray        # (N,) bool: same vehicle in the row at the next state
    continuing: np.ndarray   # (N,) bool: options: the row's option still held at the next state
    next_features: np.ndarray
    next_adjacency: np.ndarray
    next_masks: np.ndarray


def acting(transitions: list[Transition]) -> list[Transition]:
    """The transitions in which some CAV acted: one with no acting row (no CAV on the road yet,
    or, in SGRL, not the learning one) teaches nothing, and a batch of only such had no TD
    error to average (a NaN loss)."""
    return [transition for transition in transitions if (transition.actions >= 0).any()]


class EpisodeAccumulator:
    def __init__(self, steps: int, gamma: float):
        self.steps, self.gamma = steps, gamma
        self.records: list[DecisionRecord] = []
        self.emitted = 0

    def add(self, record: DecisionRecord) -> list[Transition]:
        """Add a decision whose reward is known; emit the transitions now complete."""
        self.records.append(record)
        out = []
        while self.emitted + self.steps < len(self.records):
            out.append(self._transition(self.emitted, self.emitted + self.steps, terminated=False))
            self.emitted += 1
        return acting(out)

    def finish(self, final: DecisionRecord, terminated: bool) -> list[Transition]:
        """The episode ended in ``final`` (its actions unused): emit the remaining transitions."""
        self.records.append(final)
        last = len(self.records) - 1
        out = [self._transition(t, last, terminated) for t in range(self.emitted, last)]
        self.emitted = last
        return acting(out)

    def _transition(self, t: int, end: int, terminated: bool) -> Transition:
        start, stop = self.records[t], self.records[end]
        span = end - t
        ids, next_ids = np.array(start.graph.vehicle_ids), np.array(stop.graph.vehicle_ids)
        returns, global_return = np.zeros_like(start.own), np.zeros((4, 2))
        continuing = np.zeros(len(ids), bool)
        if start.choosing is not None:   # options: held to the next state if no later record chose anew
            continuing = ~np.any([self.records[t + k].choosing for k in range(1, span + 1)], axis=0)
        for k in range(span):
            record = self.records[t + k]
            same = np.array(record.graph.vehicle_ids) == ids
            returns += self.gamma ** k * np.where(same[:, None, None], record.credit(), 0.0)
            global_return += self.gamma ** k * record.total()
        return Transition(
            features=start.graph.features, adjacency=start.graph.adjacency, actions=start.actions,
            masks=start.masks, returns=returns, global_return=global_return,
            discount=0.0 if terminated else self.gamma ** span,
            alive=(ids == next_ids) & (ids != '') & stop.graph.cav_mask,
            continuing=continuing & (ids == next_ids) & (start.actions >= 0),
            next_features=stop.graph.features, next_adjacency=stop.graph.adjacency,
            next_masks=stop.masks)


def scored_rewards(batch: dict[str, np.ndarray], multipliers: np.ndarray, credit: str) -> np.ndarray:
    """(B, N) per-row rewards of a sampled batch under per-element multipliers of the reward
    vector (B, 4, 2; ``reward.weights_of_input`` of a mode's weights): each row's own credit
    (``credit='own'``) or the global return for every row."""
    size, rows = batch['returns'].shape[:2]
    multipliers = np.asarray(multipliers, np.float32).reshape(size, 8, 1)   # one matrix product a batch element
    if credit == 'own':
        return (batch['returns'].reshape(size, rows, 8) @ multipliers)[..., 0]
    rewards = (batch['global_returns'].reshape(size, 1, 8) @ multipliers)[..., 0]
    return np.repeat(rewards, rows, axis=1)


class ReplayBuffer:
    """Fixed-capacity ring of transitions for graphs of N rows, F features, A actions."""

    def __init__(self, capacity: int, num_nodes: int, num_features: int, num_actions: int):
        self.capacity, self.num_actions = capacity, num_actions
        n, f = num_nodes, num_features
        packed_n, packed_a = (n + 7) // 8, (num_actions + 7) // 8
        self.features = np.zeros((capacity, n, f), np.float32)
        self.next_features = np.zeros((capacity, n, f), np.float32)
        self.adjacency = np.zeros((capacity, n, packed_n), np.uint8)
        self.next_adjacency = np.zeros((capacity, n, packed_n), np.uint8)
        self.degrees = np.zeros((capacity, n), np.int16)   # the adjacency's row sums, summed once here, not per batch
        self.next_degrees = np.zeros((capacity, n), np.int16)
        self.actions = np.full((capacity, n), NO_ACTION, np.int16)
        self.masks = np.zeros((capacity, n, packed_a), np.uint8)
        self.next_masks = np.zeros((capacity, n, packed_a), np.uint8)
        self.returns = np.zeros((capacity, n, 4, 2), np.float32)
        self.global_returns = np.zeros((capacity, 4, 2), np.float32)
        self.discounts = np.zeros(capacity, np.float32)
        self.alive = np.zeros((capacity, n), bool)
        self.continuing = np.zeros((capacity, n), bool)
        self.size = 0
        self._next = 0
        self.num_nodes = n

    def __len__(self) -> int:
        return self.size

    def add(self, transition: Transition) -> int:
        """Store a transition (over the oldest when full); returns its index."""
        i = self._next
        self.features[i], self.next_features[i] = transition.features, transition.next_features
        for packed, degrees, adjacency in ((self.adjacency, self.degrees, transition.adjacency),
                                           (self.next_adjacency, self.next_degrees, transition.next_adjacency)):
            edges = adjacency.astype(bool)
            packed[i], degrees[i] = np.packbits(edges, axis=-1), edges.sum(-1)
        self.actions[i] = transition.actions
        self.masks[i] = np.packbits(transition.masks, axis=-1)
        self.next_masks[i] = np.packbits(transition.next_masks, axis=-1)
        self.returns[i], self.global_returns[i] = transition.returns, transition.global_return
        self.discounts[i] = transition.discount
        self.alive[i] = transition.alive
        self.continuing[i] = transition.continuing
        self._next = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        return i

    def sample(self, indices: np.ndarray) -> dict[str, np.ndarray]:
        n, a = self.num_nodes, self.num_actions
        return {
            'features': self.features[indices], 'next_features': self.next_features[indices],
            'adjacency': np.unpackbits(self.adjacency[indices], axis=-1, count=n),
            'next_adjacency': np.unpackbits(self.next_adjacency[indices], axis=-1, count=n),
            'degrees': self.degrees[indices], 'next_degrees': self.next_degrees[indices],
            'actions': self.actions[indices].astype(np.int64),
            'masks': np.unpackbits(self.masks[indices], axis=-1, count=a).view(bool),   # 0 and 1: bools as they are
            'next_masks': np.unpackbits(self.next_masks[indices], axis=-1, count=a).view(bool),
            'returns': self.returns[indices], 'global_returns': self.global_returns[indices],
            'discounts': self.discounts[indices],
            'alive': self.alive[indices], 'continuing': self.continuing[indices],
        }


class PrioritizedSampler:
    """Proportional prioritized replay (Schaul et al. 2016): index i is drawn with probability
    P(i) = p_i^alpha / sum_k p_k^alpha, and its loss weighted by w_i = (n P(i))^-beta / max_k w_k
    (n stored transitions; the max over the buffer, so weights are at most 1). A new transition
    gets the largest priority seen so far; after an update its priority is |TD error| + epsilon."""

    def __init__(self, capacity: int, alpha: float, beta: float, epsilon: float = 1e-3):
        self.alpha, self.beta, self.epsilon = alpha, beta, epsilon
        self.priorities = np.zeros(capacity, np.float64)   # p_i^alpha
        self.size = 0
        self.max_priority = 1.0

    def added(self, index: int) -> None:
        self.priorities[index] = self.max_priority ** self.alpha
        self.size = max(self.size, index + 1)

    def probabilities(self) -> np.ndarray:
        scaled = self.priorities[:self.size]
        return scaled / scaled.sum()

    def sample(self, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(indices, importance weights) of ``count`` draws."""
        probabilities = self.probabilities()
        indices = rng.choice(self.size, size=count, p=probabilities)
        weights = (self.size * probabilities[indices]) ** -self.beta
        return indices, (weights / (self.size * probabilities.min()) ** -self.beta).astype(np.float32)

    def update(self, indices: np.ndarray, errors: np.ndarray) -> None:
        priorities = np.abs(errors) + self.epsilon
        self.priorities[indices] = priorities ** self.alpha
        self.max_priority = max(self.max_priority, float(priorities.max()))
