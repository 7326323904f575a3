"""graph_and_decision: the graph builder and the decision node composed in one process.

The same two nodes as ``graph_builder`` and ``decision_node`` (their names, parameters,
services and diagnostics: ``ros2 param set /decision_node mode CONP`` works as before), served
by one wait. The graph builder hands the decision node the episode events and each decision
step's checked states with their graph in the process; the decision node subscribes to
neither topic, and the graph is published after the commands, for the recorder and the
visualizer. So a decision step's states are decoded and checked once, not twice, and the
commands do not wait for the graph to be serialised, sent to another process and decoded
there (docs/design.md, "ROS 2 -> Speed"). The stack starts this process
(``node_table.NODES``); the two executables stay for a decision node of one's own, or a
graph builder for one's own decision maker.

Parameters given with ``--ros-args -p`` reach both nodes (each takes those it declares); a
remapping of ``__node`` would name both alike: set a node's parameter as
``-p decision_node:mode:=CONP`` if needed. The decision node's counters of its own streams
(``skipped_*``, ``dropped_*``, ``rejected_*`` of states and graphs) are the graph builder's here:
it alone takes the states.
"""
from __future__ import annotations

from exit_decision.ros.executor import run_node
from exit_decision.errors import ParameterError
from exit_decision.ros.nodes.decision_node import DecisionNode
from exit_decision.ros.nodes.graph_builder import GraphBuilderNode


def make_nodes() -> list:
    """The two nodes, made decision node first (its policies start loading at once). One
    process has one scheduling: a ``thread_priority`` or ``cpu_affinity`` that differs between
    them is refused."""
    decision = DecisionNode(composed=True)
    builder = GraphBuilderNode(decision)
    for name in ('thread_priority', 'cpu_affinity'):
        values = {node.get_name(): node.get_parameter(name).value for node in (builder, decision)}
        values = {node: value if isinstance(value, int) else sorted(set(value)) for node, value in values.items()}
        if len({str(value) for value in values.values()}) > 1:
            raise ParameterError(f'parameter {name}: {values} differ; allowed: one value for both nodes of the '
                                 f'process')
    return [builder, decision]


def main() -> int:
    return run_node('graph_and_decision', make_nodes)


if __name__ == '__main__':
    raise SystemExit(main())
