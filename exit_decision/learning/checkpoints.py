"""The checkpoint files of a training run directory, and what each says about its run.

Every checkpoint describes itself (``run_description``: method, mode, encoder, network inputs,
action space, the training config; then the revision and the progress when it was saved), so a
policy loads and checks without its run directory. The files: ``candidates/episode_<n>.pt``
(the checkpoints validation judges; the best is copied to ``policy.pt``), ``last.pt`` (the
resumable state: networks, optimizer, progress, random generator) and ``timing.json``.
"""
from __future__ import annotations

import json
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from exit_decision.config import ActionSpaceName, ProjectConfig
from exit_decision.errors import PolicyError
from exit_decision.learning.agent import GraphQAgent
from exit_decision.model.names import CONDITIONED
from exit_decision.model.networks import GraphQNetwork
from exit_decision.model.policy import CHECKPOINT_FORMAT, load_policy


def git_revision() -> str:
    """The checkout's revision (commands run from the repository root), 'unknown' elsewhere."""
    try:
        result = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True,
                                check=False, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return 'unknown'
    return result.stdout.strip() or 'unknown'


def save_policy(path: Path, network: GraphQNetwork, metadata: dict[str, Any],
                members: tuple[GraphQNetwork, ...] = ()) -> None:
    """Write a checkpoint (``model.policy.load_policy`` reads it); ``metadata`` must be plain
    data (str, numbers, lists, dicts); ``members``: an ensemble's other networks, of ``network``'s shape."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(path.suffix + '.tmp')
    torch.save({'format': CHECKPOINT_FORMAT, 'network': network.shape.to_dict(),
                'state_dict': network.state_dict(), 'metadata': metadata,
                **({'members': [member.state_dict() for member in members]} if members else {})}, temporary)
    temporary.replace(path)


@dataclass
class TrainingState:
    """A run's progress, kept in last.pt: RL episodes and decisions done, updates made, the
    best validation score so far."""
    episode: int = 0
    decisions: int = 0
    updates: int = 0
    best_score: float = -np.inf


def run_description(config: ProjectConfig, algorithm: str, mode: str, seed: int, action_space: ActionSpaceName,
                    encoder_settings: dict[str, Any], validation_modes: list[str], num_features: int) -> dict[str, Any]:
    """What every checkpoint of the run says about it (plain data), besides its revision and progress."""
    method = config.training.method(algorithm)
    return {
        'algorithm': algorithm, 'paper': method.paper, 'encoder': encoder_settings,
        'mode': mode, 'seed': seed, 'conditioned': mode == CONDITIONED, 'modes': validation_modes,
        'reward_variant': method.reward_variant or config.env.reward_variant, 'measures': method.measures,
        'feature_set': config.graph.feature_set,
        'num_nodes': config.graph.max_vehicles, 'num_features': num_features,
        'decision_interval': config.env.decision_interval, 'action_grid': config.env.actions.model_dump(),
        'action_space': action_space, 'multi_step': method.multi_step,
        **({'options': config.env.options.model_dump()} if action_space == 'options' else {}),
        'training': config.training.model_dump(),
    }


class Checkpoints:
    """Saves and restores ``agent`` (and the run's generator ``rng``) in ``out_dir``."""

    def __init__(self, out_dir: Path, description: dict[str, Any], agent: GraphQAgent, rng: np.random.Generator):
        self.out_dir, self.description, self.agent, self.rng = out_dir, description, agent, rng
        self.revision = git_revision()   # the checkout the run started from (a git process: once)

    def metadata(self, state: TrainingState) -> dict[str, Any]:
        """The run's description, the checkout's revision and the progress at ``state``."""
        return {**self.description, 'git_revision': self.revision, 'episode': state.episode,
                'updates': state.updates}

    def save_candidate(self, state: TrainingState) -> Path:
        """The online network as a policy checkpoint for validation; returns its path."""
        path = self.out_dir / 'candidates' / f'episode_{state.episode:05d}.pt'
        save_policy(path, self.agent.online, self.metadata(state))
        self.agent.online.train()
        return path

    def save_state(self, state: TrainingState) -> None:
        """last.pt: everything a resumed run continues from."""
        agent = self.agent
        torch.save({'online': agent.online.state_dict(), 'target': agent.target.state_dict(),
                    'optimizer': agent.optimizer.state_dict(), 'state': vars(state).copy(),
                    'rng': self.rng.bit_generator.state, 'metadata': self.metadata(state)},
                   self.out_dir / 'last.pt')

    def load_state(self, path: Path) -> TrainingState:
        """Restore a last.pt of the same method and mode; returns its progress."""
        data = torch.load(path, map_location='cpu', weights_only=True)
        theirs, ours = data['metadata'], self.description
        if theirs['algorithm'] != ours['algorithm'] or theirs['mode'] != ours['mode']:
            raise ValueError(f'{path}: a {theirs["algorithm"]}/{theirs["mode"]} run, '
                             f'not {ours["algorithm"]}/{ours["mode"]}')
        self.agent.online.load_state_dict(data['online'])
        self.agent.target.load_state_dict(data['target'])
        self.agent.optimizer.load_state_dict(data['optimizer'])
        self.rng.bit_generator.state = data['rng']
        return TrainingState(**data['state'])

    def load_network(self, path: Path) -> None:
        """Start from a policy checkpoint's network (online and target) instead of pre-training:
        a pre-trained policy fine-tuned under another setting (e.g. the lane planner)."""
        policy, shape = load_policy(path), self.agent.online.shape
        if policy.network.shape != shape:
            raise PolicyError(f'{path}: its network ({policy.network.shape}) is not this run\'s ({shape})')
        self.agent.online.load_state_dict(policy.network.state_dict())
        self.agent.target.load_state_dict(policy.network.state_dict())

    def write_timing(self, clock: dict[str, float], state: TrainingState, note: str) -> None:
        """timing.json: wall time of the run's phases (this invocation; a resumed run's own), and
        the RL episodes and decisions of the run."""
        end = time.monotonic()
        (self.out_dir / 'timing.json').write_text(json.dumps({
            'demonstrations_s': clock['demonstrations'] - clock['start'],
            'pretraining_s': clock['pretraining'] - clock['demonstrations'],
            'rl_s': end - clock['pretraining'], 'total_s': end - clock['start'], 'episodes': state.episode,
            'decisions': state.decisions, 'note': note},
            indent=2))
