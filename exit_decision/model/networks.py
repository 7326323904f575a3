"""The Q-networks of every method: per-row encoder -> GCN (optional) -> head -> Q values.

Paper 000's GQN/MDGQN: one encoder layer, a GCN layer, one head layer. Paper 001's networks
(FC 8-128-128, GCN 128, FC 128-128; NGRL: no GCN, the adjacency row in the input) and the
non-graph baselines of papers 002 / 003 (an MLP per CAV row, dueling streams for Dueling
DQN) are other ``NetworkShape`` values of the same module.

GCN layer (Kipf & Welling; paper 000, Eq. 5): Z = relu(D^-1/2 A D^-1/2 H W + b). The adjacency
the graph builder makes already has self loops, so no identity is added here. ``forward`` works
on dense batched tensors: features (B, N, F), adjacency (B, N, N); learning's
``cav_q_values`` gives the same values on selected rows only (``SelectedRows``: the vehicles
present, a sparse aggregation). N is whatever the input has: nothing here depends on the road.

A *mode-conditioned* network (``num_weights`` > 0) is Q(s, a, w): the mode's weights w (the
six numbers of ``reward.weight_input``) are appended to every row's features and to the
head's input, as in conditioned multi-objective Q-learning (Abels et al. 2019), so one
network serves every mode and any weight vector.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from itertools import pairwise

import numpy as np
import torch
from torch import nn
from torch.nn import functional


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


def inverse_sqrt_degree(degree: torch.Tensor) -> torch.Tensor:
    """D^-1/2 of each row's degree; 0 for a row with no edge."""
    return torch.where(degree > 0, degree.clamp(min=1e-12).rsqrt(), torch.zeros_like(degree))


def scaled_adjacency(adjacency: torch.Tensor, inv_sqrt: torch.Tensor) -> torch.Tensor:
    """D^-1/2 A D^-1/2 from the rows' D^-1/2 (``inverse_sqrt_degree``)."""
    return inv_sqrt.unsqueeze(-1) * adjacency * inv_sqrt.unsqueeze(-2)


def normalize_adjacency(adjacency: torch.Tensor) -> torch.Tensor:
    """D^-1/2 A D^-1/2 for a batch (B, N, N); rows with no edge (absent vehicles) stay zero."""
    adjacency = adjacency.float()
    return scaled_adjacency(adjacency, inverse_sqrt_degree(adjacency.sum(-1)))


def dueling_q(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Q = V + A - mean A (Dueling DQN)."""
    return value + advantage - advantage.mean(-1, keepdim=True)


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
        #: a row's input: its features [, its adjacency row] [, the weights]
        self.inputs = shape.num_features + (shape.num_nodes if shape.adjacency_input else 0) + w
        self.encoder = mlp([self.inputs, *shape.encoder])
        #: a row's code out of the encoder
        self.width = shape.encoder[-1] if shape.encoder else self.inputs
        if shape.gcn:
            self.gcn = GraphConvolution(self.width, shape.gcn)
        #: the head's input: the code, the neighbourhood's (GCN) [, the weights]
        self.head_inputs = self.width + shape.gcn + w
        self.head = mlp([self.head_inputs, *shape.head], final_activation=True)
        last = shape.head[-1] if shape.head else self.head_inputs
        if shape.dueling:
            self.value, self.advantage = nn.Linear(last, 1), nn.Linear(last, shape.num_actions)
        else:   # the output layer continues ``head`` (its state_dict keys stay those of earlier checkpoints)
            self.head.append(nn.Linear(last, shape.num_actions))
        self._one_graph: OneGraphForward | None = None   # made on first use (``one_graph``)

    @property
    def conditioned(self) -> bool:
        return self.shape.num_weights > 0

    def check_weights(self, weights) -> None:
        if self.conditioned and weights is None:
            raise ValueError('a mode-conditioned network needs the mode weights')

    def _with_weights(self, x: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
        """x (B, N, D) with each batch element's weights (B, W) appended to every row."""
        self.check_weights(weights)
        if not self.conditioned:
            return x
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
        return dueling_q(self.value(hidden), self.advantage(hidden))

    def forward(self, features: torch.Tensor, adjacency: torch.Tensor,
                weights: torch.Tensor | None = None) -> torch.Tensor:
        return self.q_of(self.embed(features, adjacency, weights))

    @torch.inference_mode()
    def one_graph(self, features: np.ndarray, adjacency: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """``forward`` of one graph (features (N, F) float32, adjacency (N, N) of 0/1 integers,
        as ``TrafficGraph`` has them), for greedy decisions: the (N, A) Q values, bit-identical
        to ``forward``'s, with less overhead a call (``OneGraphForward``)."""
        if self._one_graph is None:
            self._one_graph = OneGraphForward(self)
        return self._one_graph(features, adjacency, weights)

    def cav_q_values(self, features: torch.Tensor, selected: SelectedRows,
                     weights: torch.Tensor | None = None) -> torch.Tensor:
        """Q values (R, A) of ``selected``'s rows only, for learning: ``forward``'s values on
        those rows (equal up to rounding) without its work on rows nothing depends on. The
        encoder runs on the vehicles present only (a quarter of a batch's padded rows); the
        weights enter its first layer as their own term, once per graph, not copied to every
        row; the GCN aggregates into the selected rows only, before its linear map (a third of
        the rows); the head runs on them only."""
        self.check_weights(weights)
        graph_of_row = selected.rows[:, 0]
        if not self.shape.encoder:   # the rows' inputs (with the weights) are the code
            return self.q_of(self.embed(features, selected.adjacency, weights)[graph_of_row, selected.rows[:, 1]])
        inputs = features.flatten(0, 1).index_select(0, selected.present)
        if self.shape.adjacency_input:
            rows = selected.adjacency.flatten(0, 1).index_select(0, selected.present)
            inputs = torch.cat([inputs, rows.to(inputs.dtype)], dim=-1)
        first, *rest = self.encoder
        code = functional.linear(inputs, first.weight[:, :inputs.shape[-1]], first.bias)
        if self.conditioned:
            weights = weights.to(code.dtype)
            code = code + functional.linear(weights, first.weight[:, inputs.shape[-1]:]).index_select(
                0, selected.present_graph)
        for layer in rest:
            code = layer(code)
        parts = [code.index_select(0, selected.place)]
        if self.shape.gcn:   # Â(HW + b) = (ÂH)W + (Â1)b: the linear map on the selected rows only
            linear = self.gcn.linear
            aggregated = torch.sparse.mm(selected.aggregation.to(code.dtype), code)
            parts.append(torch.relu(torch.addmm(torch.outer(selected.aggregation_sums.to(code.dtype), linear.bias),
                                                aggregated, linear.weight.t())))
        if self.conditioned:
            parts.append(weights.index_select(0, graph_of_row))
        return self.q_of(torch.cat(parts, dim=-1))


@dataclass(frozen=True)
class SelectedRows:
    """Rows (R, 2) = (batch index, row) of a batch of graphs to value, with what
    ``GraphQNetwork.cav_q_values`` needs of the graphs' structure: made once per batch and shared
    by every network valuing the same rows (an update's target and online networks on the next
    states)."""
    rows: torch.Tensor
    #: (R,) the same rows as indices of the batch's B x N rows
    flat: torch.Tensor
    #: (B, N, N) of 0 and 1, as the replay gives it
    adjacency: torch.Tensor
    #: (P,) the rows the encoder runs on (a vehicle: an edge; or selected), as indices of the
    #: batch's B x N rows (flat indices: ``index_select`` is several times faster than masks)
    present: torch.Tensor
    #: (P,) the batch index of each present row, in ``present``'s order
    present_graph: torch.Tensor
    #: (R,) each selected row's place among the present rows
    place: torch.Tensor
    #: (R, P) sparse: the selected rows of D^-1/2 A D^-1/2, over the present rows
    aggregation: torch.Tensor
    #: (R,) each selected row's sum of ``aggregation`` (what the GCN's bias is scaled by)
    aggregation_sums: torch.Tensor

    @classmethod
    def of(cls, adjacency: torch.Tensor, rows: torch.Tensor, degree: torch.Tensor | None = None) -> SelectedRows:
        """``degree``: the rows' degrees (B, N), when known (the replay stores them; they are
        ``adjacency``'s row sums), else summed here."""
        n = adjacency.shape[1]
        degree = adjacency.sum(-1, dtype=torch.float32) if degree is None else degree.to(torch.float32)
        selected = rows[:, 0] * n + rows[:, 1]   # flat
        present = (degree > 0).reshape(-1).index_fill_(0, selected, True)
        place = present.cumsum(0) - 1             # a present row's place among the present rows
        present_rows = present.nonzero().squeeze(1)
        inverse_sqrt = inverse_sqrt_degree(degree).reshape(-1)
        selected_adjacency = adjacency.reshape(-1, n).index_select(0, selected)   # (R, N)
        edge, neighbour = selected_adjacency.nonzero(as_tuple=True)   # (selected row, neighbour), sorted
        neighbour = rows[:, 0].index_select(0, edge) * n + neighbour     # flat
        values = inverse_sqrt.index_select(0, selected).index_select(0, edge) * inverse_sqrt.index_select(0, neighbour)
        aggregation = torch.sparse_coo_tensor(   # sorted, unique (edge, place) pairs: coalesced; A's entries are 1
            torch.stack([edge, place.index_select(0, neighbour)]), values, (len(rows), len(present_rows)),
            is_coalesced=True, check_invariants=False)
        sums = torch.zeros(len(rows)).index_add_(0, edge, values)
        return cls(rows, selected, adjacency, present_rows, present_rows // n, place.index_select(0, selected),
                   aggregation, sums)

    def at(self, tensor: torch.Tensor) -> torch.Tensor:
        """``tensor`` (B, N, ...) at the selected rows: ``tensor[rows[:, 0], rows[:, 1]]``."""
        return tensor.flatten(0, 1).index_select(0, self.flat)


class OneGraphForward:
    """``GraphQNetwork.forward`` for one graph at a time, without its per-call overhead (a
    decision of the node, evaluation, acting in training: one graph, no gradient). The same
    operations on the same values in the same order, so the Q values are bit-identical (a
    test compares them for the shapes of every method of config/training.yaml and more), but:
    no module calls (the layers' ``functional`` operations directly), the rows' inputs and the
    head's inputs written into buffers kept per row count instead of expanded and concatenated
    anew, and D^-1/2 looked up per degree (computed once by ``inverse_sqrt_degree`` itself).
    The shipped network (N = 60), back to back: 0.16-0.23 ms a call against 0.24-0.35 ms. One
    caller at a time: the buffers are shared (the decision node warms a policy up in its
    loading thread and decides in the executor's, one after the other)."""

    def __init__(self, network: GraphQNetwork):
        self.network, self.shape = network, network.shape
        for layer in (*network.encoder, *network.head):
            if not isinstance(layer, nn.Linear | nn.ReLU):
                raise TypeError(f'OneGraphForward knows Linear and ReLU layers, not {type(layer).__name__}')
        self.buffers: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    def _buffers(self, rows: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The inputs and the head's inputs of ``rows`` rows, and D^-1/2 of every degree a
        graph of ``rows`` rows can have."""
        if rows not in self.buffers:
            network = self.network
            self.buffers[rows] = (torch.empty(rows, network.inputs), torch.empty(rows, network.head_inputs),
                                  inverse_sqrt_degree(torch.arange(rows + 1, dtype=torch.float32)))
        return self.buffers[rows]

    @staticmethod
    def _run(layers: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        """``layers(x)``: each Linear and ReLU as its module's ``forward`` computes it."""
        for layer in layers:
            x = functional.linear(x, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else torch.relu(x)
        return x

    def __call__(self, features: np.ndarray, adjacency: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
        network, shape = self.network, self.shape
        network.check_weights(weights)
        rows, f = len(features), shape.num_features
        if (features.shape != (rows, f) or adjacency.shape != (rows, rows) or adjacency.dtype.kind not in 'biu'
                or (shape.adjacency_input and rows != shape.num_nodes)):
            raise ValueError(f'one graph: features {features.shape} and adjacency {adjacency.shape} '
                             f'({adjacency.dtype}) do not fit; expected (N, {f}) float32 and (N, N) integers'
                             + (f', N = {shape.num_nodes}' if shape.adjacency_input else ''))
        features, adjacency = torch.from_numpy(features), torch.from_numpy(adjacency)
        inputs, head_inputs, inverse_sqrt = self._buffers(rows)
        inputs[:, :f] = features
        if shape.adjacency_input:
            inputs[:, f:f + shape.num_nodes] = adjacency
        if network.conditioned:
            w = torch.as_tensor(weights, dtype=torch.float32)
            inputs[:, -shape.num_weights:] = w
            head_inputs[:, -shape.num_weights:] = w
        encoded = self._run(network.encoder, inputs)
        head_inputs[:, :network.width] = encoded
        if shape.gcn:
            normalized = scaled_adjacency(adjacency, inverse_sqrt[adjacency.sum(-1)])
            linear = network.gcn.linear
            aggregated = torch.bmm(normalized.unsqueeze(0),
                                   functional.linear(encoded, linear.weight, linear.bias).unsqueeze(0))[0]
            head_inputs[:, network.width:network.width + shape.gcn] = torch.relu(aggregated)
        hidden = self._run(network.head, head_inputs)
        if shape.dueling:
            value, advantage = network.value, network.advantage
            hidden = dueling_q(functional.linear(hidden, value.weight, value.bias),
                               functional.linear(hidden, advantage.weight, advantage.bias))
        return hidden.numpy()
