"""How policy runs are named and where their checkpoints are, free of torch: the decision node
plans what it will load (and answers parameter requests) before it imports the policy module.

A learned method's run is ``<method>_<mode>`` (one policy per mode of config/modes.yaml) or
``<method>_conditioned`` (one mode-conditioned policy for every mode, and any weights); its
checkpoint is ``<policy dir>/<run>/policy.pt``. An *algorithm*, as the decision node, replay
and ``exit-decision stack`` take it, is ``<method>`` (its per-mode policies) or
``<method>_conditioned``. A method trained over options (``train --action-space options``)
has ``_options`` after the method's name: ``mdgqn_options_conditioned``, ``gqn_options_AGGI``.
Only mode-conditioned policies ship; per-mode ones are trained with ``train --conditioning
<mode>`` and loaded from a policy directory given.
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

#: the conditioning of a mode-conditioned training run (``exit-decision train --conditioning conditioned``)
CONDITIONED = 'conditioned'
#: run names and algorithms of mode-conditioned policies end so: policies/mdgqn_conditioned/policy.pt
CONDITIONED_SUFFIX = f'_{CONDITIONED}'
#: the action space of an algorithm whose method's name ends so (else: the 81-action grid)
OPTIONS_SUFFIX = '_options'
#: the shipped mode-conditioned MDGQN over options: the stack's algorithm, the policy of
#: tradeoff, report and the README's table
DEFAULT_ALGORITHM = 'mdgqn' + OPTIONS_SUFFIX + CONDITIONED_SUFFIX
#: the mode-conditioned MDGQN on paper 000's 81-action grid (the comparison sweep's policy)
GRID_ALGORITHM = 'mdgqn' + CONDITIONED_SUFFIX
#: the algorithms whose policies are shipped in policies/, all mode-conditioned (no per-mode one
#: ships: the first recipe's were stale, issue 39)
SHIPPED_ALGORITHMS = (GRID_ALGORITHM, DEFAULT_ALGORITHM, 'gqn' + OPTIONS_SUFFIX + CONDITIONED_SUFFIX)
#: a planned policy: (algorithm, mode), mode None for a conditioned algorithm's one policy
Planned = tuple[str, str | None]


#: what the pages call a policy beside its name (the other policies: by name alone)
ROLES = {DEFAULT_ALGORITHM: 'the shipped policy', GRID_ALGORITHM: "the grid's MDGQN"}


def described(name: str) -> str:
    """A policy's name as a figure's title and the results page's training runs give it: the
    grid's MDGQN says so (not the shipped policy: a figure may outlive what ships)."""
    return f'{name} ({ROLES[name]})' if name == GRID_ALGORITHM else name


def is_conditioned(algorithm: str) -> bool:
    """One mode-conditioned policy for every mode (``<method>_conditioned``)."""
    return algorithm.endswith(CONDITIONED_SUFFIX)


def method_of(algorithm: str) -> str:
    """The learned method of config/training.yaml an algorithm is of."""
    return algorithm.removesuffix(CONDITIONED_SUFFIX).removesuffix(OPTIONS_SUFFIX)


def action_space_of(algorithm: str) -> str:
    """'options' for ``<method>_options[_conditioned]``, else 'grid'."""
    return 'options' if algorithm.removesuffix(CONDITIONED_SUFFIX).endswith(OPTIONS_SUFFIX) else 'grid'


def algorithm_name(method: str, action_space: str, conditioned: bool) -> str:
    """The algorithm (and run name stem) of a method trained over ``action_space``."""
    return method + (OPTIONS_SUFFIX if action_space == 'options' else '') + (CONDITIONED_SUFFIX if conditioned else '')


def planned(algorithm: str, mode: str | None) -> Planned:
    """The policy that drives ``algorithm`` at ``mode``: the conditioned one whatever the mode."""
    return (algorithm, None) if is_conditioned(algorithm) else (algorithm, mode)


def planned_policies(algorithms: Iterable[str], modes: Iterable[str]) -> list[Planned]:
    """The policies to load for these algorithms and modes, in that order."""
    modes = list(modes)
    return [planned(algorithm, mode) for algorithm in algorithms
            for mode in ([None] if is_conditioned(algorithm) else modes)]


def run_name(algorithm: str, mode: str | None) -> str:
    """The run (its directory's name) of the policy that drives ``algorithm`` at ``mode``."""
    algorithm, mode = planned(algorithm, mode)
    return algorithm if mode is None else f'{algorithm}_{mode}'


def policy_path(policy_dir: Path, algorithm: str, mode: str | None = None) -> Path:
    """``<policy_dir>/<algorithm>[_<mode>]/policy.pt``: the checkpoint that drives ``algorithm`` at ``mode``."""
    return policy_dir / run_name(algorithm, mode) / 'policy.pt'


def default_policy_dir() -> Path:
    """The repository's policies/ when run from a checkout, else the installed share dir."""
    from exit_decision.config import default_config_dir
    return default_config_dir().parent / 'policies'
