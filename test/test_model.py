"""The model floor: importable without torch, policy names and paths, checkpoints' action space,
modes both ways, and the policies of a configuration loaded, checked and deciding for the
weights they are given."""
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.shield import Shield
from exit_decision.config import ConfigError
from exit_decision.errors import PolicyError
from exit_decision.graph import FEATURE_SETS, TrafficGraph
from exit_decision.model.modes import CUSTOM_MODE, ModeWeights, check_weights
from exit_decision.model.names import (DEFAULT_ALGORITHM, GRID_ALGORITHM, SHIPPED_ALGORITHMS, default_policy_dir, is_conditioned,
                                       method_of, planned_policies, policy_path)
from exit_decision.reward import weight_input
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import TrafficSnapshot


def test_the_model_package_its_names_and_modes_import_no_torch():
    """The decision node plans its policies and answers parameters before torch is loaded."""
    code = ('import sys, exit_decision.model, exit_decision.model.names, exit_decision.model.modes; '
            'print("torch" in sys.modules)')
    result = subprocess.run([sys.executable, '-c', code], cwd=Path(__file__).resolve().parent.parent,
                            capture_output=True, text=True, check=True)
    assert result.stdout.strip() == 'False'


def test_policy_names_and_paths_follow_one_rule(project_config):
    assert is_conditioned(DEFAULT_ALGORITHM) and method_of(DEFAULT_ALGORITHM) == 'mdgqn'
    assert planned_policies(['gqn', DEFAULT_ALGORITHM], ['AGGI', 'CONP']) == [
        ('gqn', 'AGGI'), ('gqn', 'CONP'), (DEFAULT_ALGORITHM, None)]
    root = Path('/p')
    assert policy_path(root, 'gqn', 'AGGI') == root / 'gqn_AGGI' / 'policy.pt'
    assert policy_path(root, DEFAULT_ALGORITHM, 'AGGI') == root / DEFAULT_ALGORITHM / 'policy.pt'
    for algorithm, mode in planned_policies(SHIPPED_ALGORITHMS, project_config.mode_matrix.modes):
        assert policy_path(default_policy_dir(), algorithm, mode).is_file(), 'every shipped policy is where the rule says'


def test_only_mode_conditioned_policies_ship():
    """The first recipe's per-mode networks were stale (issue 39): no per-mode policy ships, and
    the decision node loads none by default."""
    from exit_decision.model.policy import load_policy

    shipped = sorted(default_policy_dir().glob('*/policy.pt'))
    assert shipped and {path.parent.name: load_policy(path).mode for path in shipped} == {
        path.parent.name: None for path in shipped}
    assert all(is_conditioned(algorithm) for algorithm in SHIPPED_ALGORITHMS)


def test_checkpoints_without_an_action_space_act_on_the_grid_and_an_unknown_one_is_refused(tmp_path, per_mode_policies):
    import torch

    from exit_decision.model.policy import load_policy

    per_mode = policy_path(per_mode_policies, 'gqn', 'AGGI')
    data = torch.load(per_mode, weights_only=True)
    assert 'action_space' not in data['metadata'] and load_policy(per_mode).action_space == 'grid'
    data['metadata']['action_space'] = 'thoughts'
    torch.save(data, tmp_path / 'policy.pt')
    with pytest.raises(PolicyError, match="action space 'thoughts' is not known; known: grid, options"):
        load_policy(tmp_path / 'policy.pt')
    data['metadata']['action_space'] = 'grid'
    torch.save(data, tmp_path / 'policy.pt')
    assert load_policy(tmp_path / 'policy.pt').action_space == 'grid'


@pytest.mark.parametrize('weights, reason', [
    ([0.25, 0.35, 0.15, 0.25, 0.6, 0.4], None),
    ([0.25, 0.35, 0.15, 0.25, 0.6], 'expected 6 numbers'),
    ([0.5, 0.35, 0.15, 0.25, 0.6, 0.4], 'sum to 1, they sum to 1.25'),
    ([0.25, 0.35, 0.15, 0.25, 0.7, 0.4], 'incentive \\+ punishment must be 1'),
    ([1.2, -0.2, 0, 0, 0.5, 0.5], 'finite number >= 0'),
])
def test_weight_inputs_are_checked_with_a_reason(weights, reason):
    result = check_weights(weights)
    if reason is None:
        assert result is None
    else:
        assert re.search(reason, result)


def test_a_mode_is_one_value_made_from_its_name_or_its_weights(project_config):
    modes = ModeWeights(project_config)
    for name, config_mode in project_config.modes.items():
        mode = modes.mode(name)
        assert mode.name == name and name in modes
        np.testing.assert_array_equal(mode.weights, weight_input(config_mode))
        assert modes.of_weights(mode.weights).name in project_config.modes
    aggressive = modes.mode('AGGI').weights
    assert modes.of_weights(aggressive.tolist()).name == 'AGGI' and modes.of_weights(aggressive + 1e-12).name == 'AGGI'
    assert modes.of_weights([0.25, 0.25, 0.25, 0.25, 0.5, 0.5]).name == CUSTOM_MODE and CUSTOM_MODE not in modes
    with pytest.raises(ConfigError, match="unknown mode 'FAST'"):
        modes.mode('FAST')
    with pytest.raises(ValueError, match='sum to 1'):
        modes.of_weights([0.5, 0.5, 0.5, 0.5, 0.5, 0.5])


@pytest.fixture(scope='module')
def deciding(project_config):
    """The shield, lane planner and an idle graph (no CAV) of the shipped config."""
    config = project_config
    shield = Shield.of(config, ActionGrid(config.env.actions), RoadGeometry.of(config.scenario.road))
    n, f = config.graph.max_vehicles, len(FEATURE_SETS[config.graph.feature_set])
    idle = TrafficGraph(np.zeros((n, f), np.float32), np.zeros((n, n), np.uint8), np.zeros(n, bool), ('',) * n)
    return shield, LanePlanner.of(config, shield), idle


def test_policies_load_by_algorithm_and_mode_and_drive_in_the_mode_bound(project_config, deciding, per_mode_policies):
    """The shipped (conditioned) policies, and per-mode ones of a policy directory given."""
    from exit_decision.driving.policy import policy_driver
    from exit_decision.model.policy import load_controllers

    shield, planner, idle = deciding
    modes = ModeWeights(project_config)
    matrix = project_config.mode_matrix.modes
    controllers = load_controllers(project_config, default_policy_dir(), planned_policies(SHIPPED_ALGORITHMS, matrix),
                                   shield, planner)
    assert {algorithm: c.policy.action_space for (algorithm, mode), c in controllers.items()} == {
        GRID_ALGORITHM: 'grid', DEFAULT_ALGORITHM: 'options', 'gqn_options_conditioned': 'options'}
    controllers.update(load_controllers(project_config, per_mode_policies, planned_policies(['gqn'], matrix),
                                        shield, planner))
    assert all(controllers[('gqn', mode)].policy.mode == mode for mode in matrix)
    empty = TrafficSnapshot([])
    conditioned = policy_driver(controllers[(GRID_ALGORITHM, None)], project_config)
    with pytest.raises(PolicyError, match='no mode set'):
        conditioned.decide(idle, empty, 0.0)
    for mode in matrix:
        conditioned.set_mode(modes.mode(mode))
        conditioned.decide(idle, empty, 0.0)
    conditioned.set_mode(modes.of_weights([0.25, 0.25, 0.25, 0.25, 0.5, 0.5]))   # any point
    conditioned.decide(idle, empty, 0.0)
    per_mode = policy_driver(controllers[('gqn', 'AGGI')], project_config, modes.mode('AGGI'))   # its own mode
    per_mode.decide(idle, empty, 0.0)
    for other in (modes.mode('CONP'), modes.of_weights([0.25, 0.25, 0.25, 0.25, 0.5, 0.5])):
        with pytest.raises(PolicyError) as refused:   # refused when bound, not at the first decision
            per_mode.set_mode(other)
        message = str(refused.value)
        assert '\n' not in message and "a policy of mode 'AGGI' decides for that mode only" in message
    assert per_mode.mode.name == 'AGGI', 'a refused mode changes nothing'


def test_a_policy_that_does_not_fit_its_plan_is_refused(project_config, deciding, per_mode_policies):
    from exit_decision.model.policy import load_controller

    shield, planner, _ = deciding
    per_mode = policy_path(per_mode_policies, 'gqn', 'AGGI')
    with pytest.raises(PolicyError, match="a policy of mode 'AGGI'; algorithm 'gqn' at mode 'CONP' needs one"):
        load_controller(project_config, per_mode, shield, planner, ('gqn', 'CONP'))
    with pytest.raises(PolicyError, match='not a mode-conditioned policy'):
        load_controller(project_config, per_mode, shield, planner, ('gqn_conditioned', None))
    conditioned = policy_path(default_policy_dir(), GRID_ALGORITHM)
    with pytest.raises(PolicyError, match="a mode-conditioned policy; algorithm 'mdgqn' needs one per mode"):
        load_controller(project_config, conditioned, shield, planner, ('mdgqn', 'AGGI'))


def test_a_checkpoint_names_its_run_by_the_naming_rule(project_config, per_mode_policies):
    from exit_decision.model.policy import load_policy

    for policy_dir, algorithms in ((default_policy_dir(), SHIPPED_ALGORITHMS), (per_mode_policies, ['gqn', 'mdgqn'])):
        for algorithm, mode in planned_policies(algorithms, project_config.mode_matrix.modes):
            path = policy_path(policy_dir, algorithm, mode)
            assert load_policy(path).run_name == path.parent.name, 'evaluate and compare name a run as its directory'
