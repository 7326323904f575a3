"""The model floor: importable without torch, policy names and paths, checkpoints' action space."""
import subprocess
import sys
from pathlib import Path

import pytest

from exit_decision.errors import PolicyError
from exit_decision.model.names import (DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS, default_policy_dir, is_conditioned,
                                       method_of, planned_policies, policy_path)


def test_the_model_package_and_its_names_import_no_torch():
    """The decision node plans its policies and answers parameters before torch is loaded."""
    code = 'import sys, exit_decision.model, exit_decision.model.names; print("torch" in sys.modules)'
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


def test_checkpoints_without_an_action_space_act_on_the_grid_and_an_unknown_one_is_refused(tmp_path):
    import torch

    from exit_decision.model.policy import load_policy

    shipped = policy_path(default_policy_dir(), 'gqn', 'AGGI')
    assert load_policy(shipped).action_space == 'grid'
    data = torch.load(shipped, weights_only=True)
    data['metadata']['action_space'] = 'options'
    torch.save(data, tmp_path / 'policy.pt')
    with pytest.raises(PolicyError, match="action space 'options' is not known; known: grid"):
        load_policy(tmp_path / 'policy.pt')
    data['metadata']['action_space'] = 'grid'
    torch.save(data, tmp_path / 'policy.pt')
    assert load_policy(tmp_path / 'policy.pt').action_space == 'grid'
