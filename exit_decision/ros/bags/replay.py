"""Offline replay: re-run a decision policy on the graphs and states recorded in a bag.

For every recorded command array, the policy (the recorded one, another mode, or a given
checkpoint) decides again, for the recorded or given mode (a per-mode checkpoint refuses
another mode's), on the graph and states of the same step, under the shield; the
report counts the CAV commands that match the recorded ones and lists where they differ.
A policy over options decides the episode's steps in order, as the node did
(``driving.policy.PolicyDriver``: options held from step to step, all ended at an episode's
start and where the recorded mode or policy changes), and the options it holds are compared
with the recorded ones (/exit_decision/cav_options) too.
With ``rebuild_graph`` the graphs are not the recorded ones but those the current graph
builder makes from the recorded states (as the graph_builder node does: each episode from its
first step), so a change to the graph module shows too.
A bag that is missing, empty (no recorded commands), unfinished or corrupt raises BagError.

The replay fixture (``test/fixtures/replay_bag``: a short bag of the shipped stack and the
config override it was recorded with) is the regression test of every decision: CI replays
it and requires every command back; ``record_fixture`` (``exit-decision fixture record``)
makes it again when a policy, the shield, the lane planner or the graph change on purpose.
"""
from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from exit_decision.config.seeds import TEST_SEED
from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig, default_config_dir, deep_merge, load_project, load_yaml
from exit_decision.errors import UsageError
from exit_decision.graph import GraphBuilder, GraphCapacityError, GraphInputError, TrafficGraph
from exit_decision.model.modes import ModeWeights
from exit_decision.model.names import DEFAULT_ALGORITHM, default_policy_dir, planned, policy_path
from exit_decision.driving.policy import PolicyDriver, policy_driver
from exit_decision.model.policy import ACTION_SPACES, load_controller
from exit_decision.ros.bags.storage import BagError, read_messages
from exit_decision.ros.messages.conversions import commands_from_msg, graph_from_msg, options_from_msg, states_from_msg
from exit_decision.ros.topics import COMMANDS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC, OPTIONS_TOPIC, STATES_TOPIC
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import TrafficSnapshot


@dataclass
class ReplayReport:
    decisions: int = 0            # recorded command arrays replayed
    commands: int = 0             # CAV commands compared
    matching: int = 0
    missing_inputs: int = 0       # command arrays whose graph or states are not in the bag
    custom_weights: int = 0       # decided at custom reward_weights, which the bag does not hold
    options: int = 0              # recorded options of CAVs compared (a policy over options)
    matching_options: int = 0
    differences: list[str] = field(default_factory=list)

    @property
    def reproduced(self) -> bool:
        """Every recorded command decided again, and the same."""
        return self.commands > 0 and self.matching == self.commands and not self.missing_inputs \
            and not self.custom_weights and self.matching_options == self.options

    def summary(self, limit: int = 20) -> str:
        share = self.matching / self.commands if self.commands else float('nan')
        lines = [f'{self.decisions} decisions, {self.commands} CAV commands: {self.matching} match '
                 f'({share:.1%}); {self.missing_inputs} decisions without recorded inputs'
                 + (f', {self.custom_weights} at custom reward_weights (not replayable)' if self.custom_weights else '')
                 + (f'; {self.options} CAV options: {self.matching_options} match' if self.options else '')]
        lines += [f'  {d}' for d in self.differences[:limit]]
        if len(self.differences) > limit:
            lines.append(f'  ... and {len(self.differences) - limit} more differences')
        return '\n'.join(lines)


def rebuilt_graphs(config: ProjectConfig, states: Mapping[tuple[int, int], object],
                   wanted: set[tuple[int, int]]) -> dict[tuple[int, int], TrafficGraph]:
    """The graphs of the ``wanted`` steps that the graph builder makes from the recorded states,
    fed the decision steps of an episode in order, as the node and the environment (slots are
    kept per episode). A step it refuses (the node would have published no graph) is left out."""
    road = config.scenario.road
    builder = GraphBuilder(config.graph, RoadGeometry.of(road).road_length, road.highway_speed_limit, road.lane_count)
    graphs, episode = {}, None
    for key in sorted(states):
        if key[0] != episode:
            builder.reset()
            episode = key[0]
        if key[1] % config.env.decision_interval:
            continue
        try:
            graph = builder.build(states_from_msg(states[key], road.names.sections))
            if key in wanted:
                graphs[key] = graph
        except (GraphInputError, GraphCapacityError):
            continue
    return graphs


def replay_decisions(bag: Path, config: ProjectConfig, policy_dir: Path, mode: str | None = None,
                     algorithm: str | None = None, policy_file: Path | None = None,
                     rebuild_graph: bool = False) -> ReplayReport:
    """BagError if the bag cannot be read or holds no recorded commands."""
    graph_msgs, states, options, recorded = {}, {}, {}, []
    topics = {STATES_TOPIC, COMMANDS_TOPIC, OPTIONS_TOPIC} | (set() if rebuild_graph else {GRAPH_TOPIC})
    for topic, _, _, msg in read_messages(bag, topics):
        key = (msg.episode, msg.step)
        {GRAPH_TOPIC: graph_msgs, STATES_TOPIC: states, OPTIONS_TOPIC: options}.get(topic, {})[key] = msg
        if topic == COMMANDS_TOPIC:
            recorded.append(msg)
    if not recorded:
        raise BagError(f'{bag}: no recorded commands ({COMMANDS_TOPIC}); allowed: a bag the stack recorded with '
                       f'its decision node running')
    wanted = {(msg.episode, msg.step) for msg in recorded}
    graphs = rebuilt_graphs(config, states, wanted) if rebuild_graph else \
        {key: graph_from_msg(msg) for key, msg in graph_msgs.items() if key in wanted}
    shield = Shield.of(config, ActionGrid(config.env.actions), RoadGeometry.of(config.scenario.road))
    planner = LanePlanner.of(config, shield)
    modes = ModeWeights(config)
    drivers: dict[Path | tuple, PolicyDriver] = {}   # by policy file, or by planned (algorithm, mode)
    report, last = ReplayReport(), None   # last: (episode, policy, mode) of the decision before
    for msg in recorded:
        key = (msg.episode, msg.step)
        if key not in graphs or key not in states:
            report.missing_inputs += 1
            continue
        name, mode_name = algorithm or msg.algorithm, mode or msg.mode
        if mode_name not in modes:
            report.custom_weights += 1   # decided at reward_weights off the modes: not in the bag
            continue
        which = policy_file or planned(name, mode_name)
        if which not in drivers:
            controller = load_controller(config, policy_file or policy_path(policy_dir, *which), shield, planner,
                                         None if policy_file else which, ACTION_SPACES)
            drivers[which] = policy_driver(controller, config)
        if last != (msg.episode, which, mode_name):   # as the node: options end at a start or a switch
            drivers[which].set_mode(modes.mode(mode_name))
            last = (msg.episode, which, mode_name)
        vehicles = states_from_msg(states[key], config.scenario.road.names.sections)
        decision = drivers[which].decide(graphs[key], TrafficSnapshot(vehicles), key[1] * config.scenario.step_length)
        report.decisions += 1
        where = f'episode {key[0]} step {key[1]}'
        for vehicle_id, command in commands_from_msg(msg).items():
            report.commands += 1
            again = decision.commands.get(vehicle_id)
            if again is not None and again.lane_change == command.lane_change and np.isclose(
                    np.float32(again.acceleration), command.acceleration, atol=1e-4):
                report.matching += 1
            else:
                report.differences.append(f'{where} {vehicle_id} ({name} {mode_name}): recorded '
                                          f'({command.lane_change:+d}, {command.acceleration:g}), replayed '
                                          f'{"none" if again is None else f"({again.lane_change:+d}, {again.acceleration:g})"}')
        if decision.options is not None and key in options:
            for vehicle_id, held in options_from_msg(options[key]).items():
                report.options += 1
                again = decision.options.get(vehicle_id)
                if again is not None and again.index == held.index:
                    report.matching_options += 1
                else:
                    report.differences.append(f'{where} {vehicle_id}: recorded option {held.option}, replayed '
                                              f'{"none" if again is None else again.option}')
    return report


# --- the replay fixture ------------------------------------------------------------------------

#: the shipped config with these changes (keyed by config file, as --override): a short episode
FIXTURE_OVERRIDE = {'scenario': {'max_steps': 400}}
#: the stack run: the shipped conditioned policy, one episode, a mode switch half-way
FIXTURE_RUN = {'mode': 'AGGP', 'switch_to': 'CONP', 'switch_at_step': 200, 'algorithm': DEFAULT_ALGORITHM,
               'episodes': 1, 'seed': TEST_SEED}
#: what replay needs (it builds the graphs again; the graph topic would add ~9 KB a step)
FIXTURE_TOPICS = (STATES_TOPIC, COMMANDS_TOPIC, EPISODE_TOPIC, OPTIONS_TOPIC)


def check_fixture(fixture: Path, policy_dir: Path | None = None,
                  overrides: Sequence[Path | Mapping] = ()) -> ReplayReport:
    """Replay ``fixture``/bag with the shipped config plus the override.yaml beside it (and
    ``overrides``), the shipped (or ``policy_dir``'s) policies and graphs built again from its states."""
    config = load_project(None, overrides=[fixture / 'override.yaml', *overrides])
    return replay_decisions(fixture / 'bag', config, policy_dir or default_policy_dir(), rebuild_graph=True)


def record_fixture(fixture: Path, log_dir: Path) -> str:
    """Run the stack (shipped config with FIXTURE_OVERRIDE, shipped policies, FIXTURE_RUN),
    recording FIXTURE_TOPICS, check that the replay reproduces the new bag, and only then put
    it in place of ``fixture``'s; returns what was recorded. UsageError when the run or the
    check fails (the old fixture is kept)."""
    from exit_decision.ros.stack.launcher import run_stack

    fixture.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix='replay_fixture_') as scratch:
        new = Path(scratch) / 'fixture'
        config_dir = shutil.copytree(default_config_dir(), Path(scratch) / 'config')
        for name, values in FIXTURE_OVERRIDE.items():
            path = config_dir / f'{name}.yaml'
            path.write_text(yaml.safe_dump(deep_merge(load_yaml(path), values)))
        load_project(config_dir)   # fail here, naming the key, if the override no longer fits
        new.mkdir()
        (new / 'override.yaml').write_text(
            '# The replay fixture was recorded with the shipped config and this override (exit-decision fixture\n'
            '# record); test/test_replay_fixture.py replays it with the same.\n' + yaml.safe_dump(FIXTURE_OVERRIDE))
        run = run_stack(**FIXTURE_RUN, bag_path=new / 'bag', log_dir=log_dir, config_dir=str(config_dir),
                        policy_dir=str(default_policy_dir()), visualizer=False,
                        extra={'recorder': {'topics': list(FIXTURE_TOPICS)}}, timeout=900)
        if not run.episodes or not run.mode_switch.endswith('accepted'):
            raise UsageError(f'the stack run failed ({run.mode_switch or "no mode switch"}, {len(run.episodes)} '
                             f'episode(s)); logs: {log_dir}; the fixture is unchanged')
        report = check_fixture(new)
        if not report.reproduced:
            first = report.differences[0] if report.differences else report.summary(limit=0)
            raise UsageError(f'replay does not reproduce the new bag (an installed package older than the source? '
                             f'run scripts/bootstrap.sh): {first}; the fixture is unchanged')
        shutil.rmtree(fixture, ignore_errors=True)
        shutil.move(new, fixture)
    size = sum(path.stat().st_size for path in (fixture / 'bag').iterdir())
    return f'{fixture}: {run.mode_switch}; {report.summary(limit=0)}; bag {size / 1e6:.2f} MB'
