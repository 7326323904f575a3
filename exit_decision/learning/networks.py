"""The Q-networks of every method: per-row encoder -> GCN (optional) -> head -> Q values.

Paper 000's GQN/MDGQN: one encoder layer, a GCN layer, one head layer. Paper 001's networks
(FC 8-128-128, GCN 128, FC 128-128; NGRL: no GCN, the adjacency row in the input) and the
non-graph baselines of papers 002 / 003 (an MLP per CAV row, dueling streams for Dueling
DQN) are other ``NetworkShape`` values of the same module.

GCN layer (Kipf & Welling, SPEC eq. 5): Z = relu(D^-1/2 A D^-1/2 H W + b). The adjacency the
graph builder makes already has self loops, so no identity is added here. Everything works
on dense batched tensors: features (B, N, F), adjacency (B, N, N). N is whatever the input
has: nothing here depends on the road.

A *mode-conditioned* network (``num_weights`` > 0) is Q(s, a, w): the mode's weights w (the
six numbers of ``reward.weight_input``) are appended to every row's features and to the
head's input, as in conditioned multi-objective Q-learning (Abels et al. 2019), so one
network serves every mode and any weight vector.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from itertools import pairwise

import torch
from torch import nn


def _layers(value: int | Sequence[int]) -> tuple[int, ...]:
    return (value,) if isinstance(value, int) else tuple(value)


@dataclass(frozen=True)
class NetworkShape:
    """A method's network: per-row encoder layers, a GCN layer (0: none), head layers, then
    Q values (dueling: value + advantage streams). Integers are one layer (older checkpoints)."""
    num_features: int
    num_actions: int
    encoder: tuple[int, ...] = (64,)
    gcn: int = 64
    head: tuple[int, ...] = (128,)
    num_weights: int = 0      # > 0: mode-conditioned, Q(s, a, w) with w of this length
    dueling: bool = False
    adjacency_input: bool = False   # no GCN: each row's adjacency row is part of its input (NGRL)
    num_nodes: int = 0              # N, needed by adjacency_input only

    def __post_init__(self) -> None:
        object.__setattr__(self, 'encoder', _layers(self.encoder))
        object.__setattr__(self, 'head', _layers(self.head))
        if self.adjacency_input and (self.gcn or self.num_nodes <= 0):
            raise ValueError('adjacency_input needs gcn: 0 and num_nodes > 0')

    def to_dict(self) -> dict:
        return {key: list(value) if isinstance(value, tuple) else value for key, value in asdict(self).items()}


def mlp(sizes: Sequence[int], final_activation: bool = True) -> nn.Sequential:
    """Linear layers between consecutive ``sizes``, ReLU after each (but the last unless asked)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if final_activation or i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def normalize_adjacency(adjacency: torch.Tensor) -> torch.Tensor:
    """D^-1/2 A D^-1/2 for a batch (B, N, N); rows with no edge (absent vehicles) stay zero."""
    adjacency = adjacency.float()
    degree = adjacency.sum(-1)
    inv_sqrt = torch.where(degree > 0, degree.clamp(min=1e-12).rsqrt(), torch.zeros_like(degree))
    return inv_sqrt.unsqueeze(-1) * adjacency * inv_sqrt.unsqueeze(-2)


class GraphConvolution(nn.Module):
    def __init__(self, in_features: int, out_features: int):
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)

    def forward(self, features: torch.Tensor, normalized_adjacency: torch.Tensor) -> torch.Tensor:
        return torch.relu(normalized_adjacency @ self.linear(features))


class GraphQNetwork(nn.Module):
    """Q values (B, N, A) for every row; callers use the CAV rows only. With no GCN and no
    adjacency input each row is an independent MLP (the non-graph baselines)."""

    def __init__(self, shape: NetworkShape):
        super().__init__()
        self.shape = shape
        w = shape.num_weights
        inputs = shape.num_features + w + (shape.num_nodes if shape.adjacency_input else 0)
        self.encoder = mlp([inputs, *shape.encoder])
        width = shape.encoder[-1] if shape.encoder else inputs
        if shape.gcn:
            self.gcn = GraphConvolution(width, shape.gcn)
        self.head = mlp([width + shape.gcn + w, *shape.head], final_activation=True)
        last = shape.head[-1] if shape.head else width + shape.gcn + w
        if shape.dueling:
            self.value, self.advantage = nn.Linear(last, 1), nn.Linear(last, shape.num_actions)
        else:   # the output layer continues ``head`` (its state_dict keys stay those of earlier checkpoints)
            self.head.append(nn.Linear(last, shape.num_actions))

    @property
    def conditioned(self) -> bool:
        return self.shape.num_weights > 0

    def _with_weights(self, x: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
        """x (B, N, D) with each batch element's weights (B, W) appended to every row."""
        if not self.conditioned:
            return x
        if weights is None:
            raise ValueError('a mode-conditioned network needs the mode weights')
        return torch.cat([x, weights[:, None, :].expand(-1, x.shape[1], -1).to(x.dtype)], dim=-1)

    def embed(self, features: torch.Tensor, adjacency: torch.Tensor,
              weights: torch.Tensor | None = None) -> torch.Tensor:
        """Per-row embedding (B, N, encoder + gcn [+ W]): the row's own code, its
        neighbourhood's (and the weights, for the head of a conditioned network)."""
        if self.shape.adjacency_input:
            features = torch.cat([features, adjacency.to(features.dtype)], dim=-1)
        encoded = self.encoder(self._with_weights(features, weights))
        if self.shape.gcn:
            encoded = torch.cat([encoded, self.gcn(encoded, normalize_adjacency(adjacency))], dim=-1)
        return self._with_weights(encoded, weights)

    def q_of(self, embedded: torch.Tensor) -> torch.Tensor:
        """Q values from row embeddings (dueling: V + A - mean A)."""
        hidden = self.head(embedded)
        if not self.shape.dueling:
            return hidden
        advantage = self.advantage(hidden)
        return self.value(hidden) + advantage - advantage.mean(-1, keepdim=True)

    def forward(self, features: torch.Tensor, adjacency: torch.Tensor,
                weights: torch.Tensor | None = None) -> torch.Tensor:
        return self.q_of(self.embed(features, adjacency, weights))

    def cav_q_values(self, features: torch.Tensor, adjacency: torch.Tensor, rows: torch.Tensor,
                     weights: torch.Tensor | None = None) -> torch.Tensor:
        """Q values (R, A) of selected rows only, ``rows`` (R, 2) = (batch index, row): the head
        runs on those rows only."""
        embedded = self.embed(features, adjacency, weights)
        return self.q_of(embedded[rows[:, 0], rows[:, 1]])
