"""The graph Q-network of paper 000 (GQN/MDGQN share it): encoder -> GCN -> head -> Q values.

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

from dataclasses import asdict, dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class NetworkShape:
    num_features: int
    num_actions: int
    encoder: int = 64
    gcn: int = 64
    head: int = 128
    num_weights: int = 0      # > 0: mode-conditioned, Q(s, a, w) with w of this length

    def to_dict(self) -> dict:
        return asdict(self)


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
    """Q values (B, N, A) for every row; callers use the CAV rows only."""

    def __init__(self, shape: NetworkShape):
        super().__init__()
        self.shape = shape
        w = shape.num_weights
        self.encoder = nn.Sequential(nn.Linear(shape.num_features + w, shape.encoder), nn.ReLU())
        self.gcn = GraphConvolution(shape.encoder, shape.gcn)
        self.head = nn.Sequential(nn.Linear(shape.encoder + shape.gcn + w, shape.head), nn.ReLU(),
                                  nn.Linear(shape.head, shape.num_actions))

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
        encoded = self.encoder(self._with_weights(features, weights))
        embedded = torch.cat([encoded, self.gcn(encoded, normalize_adjacency(adjacency))], dim=-1)
        return self._with_weights(embedded, weights)

    def forward(self, features: torch.Tensor, adjacency: torch.Tensor,
                weights: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.embed(features, adjacency, weights))

    def cav_q_values(self, features: torch.Tensor, adjacency: torch.Tensor, rows: torch.Tensor,
                     weights: torch.Tensor | None = None) -> torch.Tensor:
        """Q values (R, A) of selected rows only, ``rows`` (R, 2) = (batch index, row): the head
        runs on those rows only."""
        embedded = self.embed(features, adjacency, weights)
        return self.head(embedded[rows[:, 0], rows[:, 1]])
