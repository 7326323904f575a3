"""An anchored policy from training runs (issue 39; ``driving.anchored``): the members' networks in
one checkpoint with their prior, and the (kappa, margin) chosen on the validation seeds.

``anchor_policy`` writes one checkpoint; ``tune_anchor`` writes one per point of a (kappa, margin)
grid, validates each against the best fixed driver of every mode on the validation seeds as the
trainer validates its candidates (``validation``; the constant options are played once, here, not
in every worker), logs ``anchor.csv`` and keeps the best by the same selection score as ``policy.pt``.
"""
from __future__ import annotations

import json
import multiprocessing
import shutil
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tqdm import tqdm

from exit_decision.config import ProjectConfig
from exit_decision.driving.anchored import Anchor
from exit_decision.env import ExitDecisionEnv
from exit_decision.errors import PolicyError
from exit_decision.evaluation.evaluate import constant_option_episodes
from exit_decision.learning.checkpoints import save_policy
from exit_decision.learning.validation import ValidationTask, selection_score, validate_checkpoint, validation_seeds
from exit_decision.model.policy import GraphPolicy, load_policy
from exit_decision.tables import append_row


def anchor_policy(members: Sequence[Path | GraphPolicy], anchor: Anchor, out: Path) -> Path:
    """Write the anchored policy of ``members`` (policies over options of one shape, conditioned,
    carrying the same prior; paths or loaded) at ``out``; PolicyError naming the member that does not fit."""
    policies = [member if isinstance(member, GraphPolicy) else load_policy(member) for member in members]
    first = policies[0]
    for policy in policies:
        if policy.action_space != 'options' or not policy.conditioned or policy.prior is None:
            raise PolicyError(f'{policy.path}: an anchored policy is made of mode-conditioned policies over options '
                              f'that carry their prior')
        if policy.network.shape != first.network.shape or policy.prior != first.prior:
            raise PolicyError(f'{policy.path}: another network shape or prior than {first.path}')
    metadata = {**first.metadata, 'anchor': anchor.to_metadata(),
                'members': [{'path': str(policy.path), 'seed': policy.metadata.get('seed'),
                             'revision': policy.metadata.get('revision')} for policy in policies]}
    save_policy(out, first.network, metadata, tuple(policy.network for policy in policies[1:]))
    return out


def tune_anchor(config: ProjectConfig, members: Sequence[Path], kappas: Sequence[float], margins: Sequence[float],
                episodes: int, out_dir: Path, jobs: int = 1, command: str = '') -> tuple[Anchor, float, dict]:
    """Every (kappa, margin) validated on ``episodes`` validation seeds in every validation mode;
    the best, by the trainer's selection score, copied to ``out_dir/policy.pt``: (its point, its score,
    its validation rows per mode); ``command``: what made them, for anchor.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    training = config.training
    seeds = validation_seeds(episodes)
    env = ExitDecisionEnv(config)   # the constant options played once here, not in every worker
    try:
        styles = constant_option_episodes(env, seeds, desc='the constant options')
    finally:
        env.close()
    task = ValidationTask(config, list(training.conditioning.validation_modes), seeds, 'options', styles)
    points = [Anchor(kappa, margin) for kappa in kappas for margin in margins]
    loaded = [load_policy(path) for path in members]   # read once, written once per point
    paths = [anchor_policy(loaded, point, out_dir / 'candidates' / f'kappa{point.kappa:g}_margin{point.margin:g}.pt')
             for point in points]
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context('spawn')) as pool:
        results = list(tqdm(pool.map(validate_checkpoint, [task] * len(paths), paths), total=len(paths),
                            desc='anchor (kappa, margin)', unit='point'))
    scores = []
    for point, per_mode in zip(points, results):
        score = selection_score(per_mode, training.validation.min_exit_rate, training.validation.max_cav_collision_rate)
        scores.append(score)
        for mode, row in per_mode.items():
            append_row(out_dir / 'anchor.csv', {'kappa': point.kappa, 'margin': point.margin, 'mode': mode, **row,
                                                'score': score})
    best = max(range(len(points)), key=scores.__getitem__)
    shutil.copyfile(paths[best], out_dir / 'policy.pt')
    (out_dir / 'anchor.json').write_text(json.dumps(
        {'command': command, 'members': [str(path) for path in members], 'kappas': list(kappas), 'margins': list(margins),
         'validation_seeds': task.seeds, 'chosen': points[best].to_metadata(), 'score': scores[best]}, indent=2))
    return points[best], scores[best], results[best]
