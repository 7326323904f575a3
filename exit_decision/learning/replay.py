"""Replay of m-step transitions between decisions, built so that windows never cross an episode.

``EpisodeAccumulator`` collects an episode's decisions (graph, actions, masks, reward) and
emits, for decision t, the transition to t + K with K = min(m, decisions left):
R = sum_k gamma^k r_{t+k}; the bootstrap discount gamma^K, or 0 when the episode terminated
inside the window; and per row whether the same vehicle is still in that row at t + K (a CAV
that left or collided gets a terminal target). ``ReplayBuffer`` stores them in flat arrays
(masks and adjacency bit-packed) and samples batches; demonstrations live in their own
buffer that is never overwritten.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from exit_decision.graph import TrafficGraph

NO_ACTION = -1


@dataclass(frozen=True)
class DecisionRecord:
    graph: TrafficGraph
    actions: np.ndarray      # (N,) int, NO_ACTION on rows that did not act
    masks: np.ndarray        # (N, A) bool, the masks the actions were chosen under
    reward: float = 0.0      # shared reward until the next decision


@dataclass(frozen=True)
class Transition:
    features: np.ndarray
    adjacency: np.ndarray
    actions: np.ndarray
    masks: np.ndarray
    ret: float
    discount: float
    alive: np.ndarray        # (N,) bool: same vehicle in the row at the next state
    next_features: np.ndarray
    next_adjacency: np.ndarray
    next_masks: np.ndarray


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
        return out

    def finish(self, final: DecisionRecord, terminated: bool) -> list[Transition]:
        """The episode ended in ``final`` (its actions unused): emit the remaining transitions."""
        self.records.append(final)
        last = len(self.records) - 1
        out = [self._transition(t, last, terminated) for t in range(self.emitted, last)]
        self.emitted = last
        return out

    def _transition(self, t: int, end: int, terminated: bool) -> Transition:
        start, stop = self.records[t], self.records[end]
        span = end - t
        ret = sum(self.gamma ** k * self.records[t + k].reward for k in range(span))
        ids, next_ids = np.array(start.graph.vehicle_ids), np.array(stop.graph.vehicle_ids)
        return Transition(
            features=start.graph.features, adjacency=start.graph.adjacency, actions=start.actions,
            masks=start.masks, ret=float(ret), discount=0.0 if terminated else self.gamma ** span,
            alive=(ids == next_ids) & (ids != '') & stop.graph.cav_mask,
            next_features=stop.graph.features, next_adjacency=stop.graph.adjacency,
            next_masks=stop.masks)


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
        self.actions = np.full((capacity, n), NO_ACTION, np.int16)
        self.masks = np.zeros((capacity, n, packed_a), np.uint8)
        self.next_masks = np.zeros((capacity, n, packed_a), np.uint8)
        self.returns = np.zeros(capacity, np.float32)
        self.discounts = np.zeros(capacity, np.float32)
        self.alive = np.zeros((capacity, n), bool)
        self.size = 0
        self._next = 0
        self.num_nodes = n

    def __len__(self) -> int:
        return self.size

    def add(self, transition: Transition) -> None:
        i = self._next
        self.features[i], self.next_features[i] = transition.features, transition.next_features
        self.adjacency[i] = np.packbits(transition.adjacency.astype(bool), axis=-1)
        self.next_adjacency[i] = np.packbits(transition.next_adjacency.astype(bool), axis=-1)
        self.actions[i] = transition.actions
        self.masks[i] = np.packbits(transition.masks, axis=-1)
        self.next_masks[i] = np.packbits(transition.next_masks, axis=-1)
        self.returns[i], self.discounts[i] = transition.ret, transition.discount
        self.alive[i] = transition.alive
        self._next = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, indices: np.ndarray) -> dict[str, np.ndarray]:
        n, a = self.num_nodes, self.num_actions
        return {
            'features': self.features[indices], 'next_features': self.next_features[indices],
            'adjacency': np.unpackbits(self.adjacency[indices], axis=-1, count=n),
            'next_adjacency': np.unpackbits(self.next_adjacency[indices], axis=-1, count=n),
            'actions': self.actions[indices].astype(np.int64),
            'masks': np.unpackbits(self.masks[indices], axis=-1, count=a).astype(bool),
            'next_masks': np.unpackbits(self.next_masks[indices], axis=-1, count=a).astype(bool),
            'returns': self.returns[indices], 'discounts': self.discounts[indices],
            'alive': self.alive[indices],
        }
