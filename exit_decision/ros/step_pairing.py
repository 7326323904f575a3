"""The graph and the vehicle states of each decision step, from two streams, paired by
(episode, step) for a node that decides on both (decision_node started alone).

Each stream has its ``input_checks.StepGate`` (what can follow the current episode and step);
an item waits at most ``PAIRING_WINDOW`` decision steps for its other half, and a graph
dropped unpaired is counted (``rejected_unpaired_graphs``).
"""
from __future__ import annotations

from collections.abc import Callable

from exit_decision.input_checks import StepGate

PAIRING_WINDOW = 20   # decision steps of unpaired graphs / states kept while waiting for the other half

Key = tuple[int, int]   # (episode, step)


class StepPairing:
    def __init__(self, max_steps: int, interval: int, count: Callable[[str], None]):
        self.interval, self.count = interval, count
        gap = 2 * interval   # one decision step may go missing without a resync
        self.graph_gate, self.states_gate = StepGate(max_steps, max_gap=gap), StepGate(max_steps, max_gap=gap)
        self.graphs: dict[Key, tuple] = {}    # (graph, stamp)
        self.states: dict[Key, list] = {}     # vehicles

    def announce(self, episode: int) -> None:
        """An episode's EVENT_STARTED: both streams may begin it."""
        for gate in (self.graph_gate, self.states_gate):
            gate.announce(episode)

    def start(self, episode: int) -> None:
        """The first item of an announced episode came: both streams follow it from its start
        (a late item of the pass before is refused on either), nothing older waits."""
        for gate in (self.graph_gate, self.states_gate):
            gate.start(episode)
        self.graphs.clear()
        self.states.clear()

    def add(self, store: dict, key: Key, item) -> tuple | None:
        """Keep a checked item of step ``key`` in ``store`` (``graphs`` or ``states``); the step's
        ((graph, stamp), vehicles) once both halves are here, else None."""
        store[key] = item
        if key not in self.graphs or key not in self.states:
            self.forget_before((key[0], key[1] - PAIRING_WINDOW * self.interval))
            return None
        pair = self.graphs.pop(key), self.states.pop(key)
        self.forget_before(key)
        return pair

    def forget_before(self, key: Key) -> None:
        for store in (self.graphs, self.states):
            for old in [k for k in store if k < key]:
                if store is self.graphs:
                    self.count('rejected_unpaired_graphs')
                del store[old]
