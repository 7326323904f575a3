"""Offline replay: re-run a decision policy on the graphs and states recorded in a bag.

For every recorded command array, the policy (the recorded one, another mode, or a given
checkpoint; a conditioned one at the recorded or given mode's weights) decides again on the
graph and states of the same step, under the shield; the
report counts the CAV commands that match the recorded ones and lists where they differ.
A bag that is missing, empty (no recorded commands), unfinished or corrupt raises BagError.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig
from exit_decision.policy import CONDITIONED_SUFFIX, PolicyController, load_policy
from exit_decision.reward import weight_input
from exit_decision.ros.bags import BagError, read_messages
from exit_decision.ros.common import COMMANDS_TOPIC, GRAPH_TOPIC, STATES_TOPIC
from exit_decision.ros.conversions import commands_from_msg, graph_from_msg, states_from_msg
from exit_decision.scenario.geometry import RoadGeometry


@dataclass
class ReplayReport:
    decisions: int = 0            # recorded command arrays replayed
    commands: int = 0             # CAV commands compared
    matching: int = 0
    missing_inputs: int = 0       # command arrays whose graph or states are not in the bag
    custom_weights: int = 0       # decided at custom reward_weights, which the bag does not hold
    differences: list[str] = field(default_factory=list)

    def summary(self, limit: int = 20) -> str:
        share = self.matching / self.commands if self.commands else float('nan')
        lines = [f'{self.decisions} decisions, {self.commands} CAV commands: {self.matching} match '
                 f'({share:.1%}); {self.missing_inputs} decisions without recorded inputs'
                 + (f', {self.custom_weights} at custom reward_weights (not replayable)' if self.custom_weights else '')]
        lines += [f'  {d}' for d in self.differences[:limit]]
        if len(self.differences) > limit:
            lines.append(f'  ... and {len(self.differences) - limit} more differences')
        return '\n'.join(lines)


def replay_decisions(bag: Path, config: ProjectConfig, policy_dir: Path, mode: str | None = None,
                     algorithm: str | None = None, policy_file: Path | None = None) -> ReplayReport:
    """BagError if the bag cannot be read or holds no recorded commands."""
    graphs, states, recorded = {}, {}, []
    for topic, _, _, msg in read_messages(bag, {GRAPH_TOPIC, STATES_TOPIC, COMMANDS_TOPIC}):
        key = (msg.episode, msg.step)
        {GRAPH_TOPIC: graphs, STATES_TOPIC: states}.get(topic, {})[key] = msg
        if topic == COMMANDS_TOPIC:
            recorded.append(msg)
    if not recorded:
        raise BagError(f'{bag}: no recorded commands ({COMMANDS_TOPIC}); allowed: a bag the stack recorded with '
                       f'its decision node running')
    grid = ActionGrid(config.env.actions)
    shield = Shield.of(config, grid, RoadGeometry.of(config.scenario.road))
    planner = LanePlanner.of(config, shield)
    controllers: dict[Path, PolicyController] = {}
    report = ReplayReport()
    for msg in recorded:
        key = (msg.episode, msg.step)
        if key not in graphs or key not in states:
            report.missing_inputs += 1
            continue
        name, mode_name = algorithm or msg.algorithm, mode or msg.mode
        if mode_name not in config.modes:
            report.custom_weights += 1   # decided at reward_weights off the modes: not in the bag
            continue
        conditioned = name.endswith(CONDITIONED_SUFFIX)
        path = policy_file or policy_dir / (name if conditioned else f'{name}_{mode_name}') / 'policy.pt'
        if path not in controllers:
            policy = load_policy(path)
            controllers[path] = PolicyController(policy, shield, np.zeros(6) if policy.conditioned else None, planner)
        controller = controllers[path]
        if controller.policy.conditioned:
            controller.weights = weight_input(config.mode(mode_name))
        decision = controller.decide(graph_from_msg(graphs[key]), states_from_msg(states[key]))
        report.decisions += 1
        for vehicle_id, command in commands_from_msg(msg).items():
            report.commands += 1
            again = grid.command(decision.actions[vehicle_id]) if vehicle_id in decision.actions else None
            if again is not None and again.lane_change == command.lane_change and np.isclose(
                    again.acceleration, command.acceleration, atol=1e-4):
                report.matching += 1
            else:
                report.differences.append(f'episode {key[0]} step {key[1]} {vehicle_id}: recorded '
                                          f'({command.lane_change:+d}, {command.acceleration:g}), replayed '
                                          f'{"none" if again is None else f"({again.lane_change:+d}, {again.acceleration:g})"}')
    return report
