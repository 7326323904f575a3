"""Helpers for the ROS integration tests: small config, random policies, node processes."""
import shutil
import subprocess
from pathlib import Path

import torch
import yaml

from exit_decision.actions import ActionGrid
from exit_decision.config import default_config_dir, load_project
from exit_decision.graph import FEATURE_SETS
from exit_decision.model.networks import GraphQNetwork, NetworkShape
from exit_decision.learning.checkpoints import save_policy

SMALL_TRAFFIC = {'HV1': 4, 'HV2': 2, 'HV3': 2, 'CAV': 4}


def small_config_dir(target: Path) -> Path:
    """The shipped config with 12 vehicles instead of 60 (short episodes)."""
    shutil.copytree(default_config_dir(), target)
    path = target / 'scenario.yaml'
    data = yaml.safe_load(path.read_text())
    for name, count in SMALL_TRAFFIC.items():
        data['vehicle_classes'][name]['count'] = count
    path.write_text(yaml.safe_dump(data))
    return target


def random_policies(config_dir: Path, target: Path, modes=('AGGI', 'AGGP', 'CONI', 'CONP')) -> Path:
    """Small untrained policies for every (algorithm, mode), a conditioned one, and the
    conditioned ones over options: the wiring, not the driving, is tested."""
    config = load_project(config_dir)
    grid = ActionGrid(config.env.actions)
    options = config.env.options
    runs = [(a, m, f'{a}_{m}') for a in ('gqn', 'mdgqn') for m in modes] + [
        ('mdgqn', 'conditioned', 'mdgqn_conditioned'), ('mdgqn', 'conditioned', 'mdgqn_options_conditioned'),
        ('gqn', 'conditioned', 'gqn_options_conditioned')]
    for index, (algorithm, mode, name) in enumerate(runs):
        torch.manual_seed(index)
        over_options = '_options' in name
        actions = len(options.lane_intents) * len(options.styles) if over_options else grid.size
        network = GraphQNetwork(NetworkShape(len(FEATURE_SETS[config.graph.feature_set]), actions, 8, 8, 8,
                                             num_weights=6 if mode == 'conditioned' else 0))
        save_policy(target / name / 'policy.pt', network, {
            'algorithm': algorithm, 'mode': mode, 'num_nodes': config.graph.max_vehicles,
            'feature_set': config.graph.feature_set, 'decision_interval': config.env.decision_interval,
            'action_grid': config.env.actions.model_dump(),
            **({'action_space': 'options', 'options': options.model_dump()} if over_options else {})})
    return target


def stop(process: subprocess.Popen, sig=2, timeout=10.0) -> int:
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode
