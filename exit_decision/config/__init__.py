"""YAML configuration: loading every file of a config directory, validated with errors that
name the file and the bad key.

Every file under ``config/`` has a pydantic schema in ``schemas``; the ones other modules use
are importable from here too, so callers name one place.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import BaseModel, ConfigDict, StringConstraints

from exit_decision.config.schemas import (
    PUBLISHED_SUFFIX, ActionGridConfig, ActionSpaceName, BaselineRewardConfig, ConfigError, EnvConfig,
    ExplorationConfig, GraphConfig, IntentionRewardConfig, MatrixRewardConfig, ModeConfig, ModeMatrix, ModesConfig,
    PrioritizedReplayConfig, RewardConfig, RewardVariantConfig, RoadConfig, RoadNames, RuleBasedConfig, SchemaT,
    ScenarioConfig, ShieldConfig, TermsRewardConfig, TrainingConfig, ValidationConfig, deep_merge, parse)

#: what callers import from here: the loading, and the schemas they name
__all__ = ['CONFIG_FILES', 'PUBLISHED_SUFFIX', 'ActionGridConfig', 'ActionSpaceName', 'BaselineRewardConfig', 'ConfigError',
           'ExplorationConfig', 'GraphConfig', 'IntentionRewardConfig', 'MatrixRewardConfig', 'ModeConfig',
           'PrioritizedReplayConfig', 'ProjectConfig', 'RewardVariantConfig', 'RoadConfig', 'RoadNames', 'RuleBasedConfig',
           'ScenarioConfig', 'ShieldConfig', 'TermsRewardConfig', 'TrainingConfig', 'ValidationConfig', 'deep_merge',
           'default_config_dir', 'load', 'load_project', 'load_variants', 'load_yaml', 'parse']


def default_config_dir() -> Path:
    """The source tree's config/ when running from a checkout, else the installed package's
    share directory (found through the ament index, as on a colcon install)."""
    in_tree = Path(__file__).resolve().parents[2] / 'config'
    if in_tree.is_dir():
        return in_tree
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        return Path(get_package_share_directory('exit_decision')) / 'config'
    except PackageNotFoundError:
        raise ConfigError('exit_decision is not in the ament index (AMENT_PREFIX_PATH): source the '
                          'install\'s setup script, or pass --config-dir') from None


def default_rviz_config() -> Path:
    """The shipped RViz view of the stack's markers (rviz/exit_decision.rviz): the checkout's or
    the install's, beside its config/."""
    return default_config_dir().parent / 'rviz' / 'exit_decision.rviz'


#: PyYAML's safe loader in C (libyaml, in PyYAML's wheels) where present: the same data, parsed
#: faster; every node loads config/ at start (load_project: 6 ms, 39 ms with the Python loader)
SAFE_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


def load_yaml(path: Path) -> object:
    try:
        with open(path, encoding='utf-8') as stream:
            return yaml.load(stream, Loader=SAFE_LOADER)
    except OSError as error:
        raise ConfigError(f'{path}: cannot read ({error.strerror})') from None
    except yaml.YAMLError as error:
        raise ConfigError(f'{path}: not valid YAML ({error})') from None


def load(schema: type[SchemaT], path: Path | str) -> SchemaT:
    path = Path(path)
    return parse(schema, load_yaml(path), path)


class ProjectConfig(BaseModel):
    """Everything the environment needs, loaded from one config directory."""
    model_config = ConfigDict(frozen=True)
    scenario: ScenarioConfig
    graph: GraphConfig
    env: EnvConfig
    modes: dict[str, ModeConfig]
    mode_matrix: ModeMatrix
    rewards: dict[str, RewardVariantConfig]
    training: TrainingConfig

    def mode(self, name: str) -> ModeConfig:
        if name not in self.modes:
            raise ConfigError(f'unknown mode {name!r}; known modes: {", ".join(self.modes)}')
        return self.modes[name]

    def reward(self, name: str) -> RewardVariantConfig:
        if name not in self.rewards:
            raise ConfigError(f'unknown reward variant {name!r}; known: {", ".join(self.rewards)}')
        return self.rewards[name]


CONFIG_FILES = {'scenario': ScenarioConfig, 'graph': GraphConfig, 'env': EnvConfig, 'modes': ModesConfig,
                'reward': RewardConfig, 'training': TrainingConfig}


def _as_mapping(source: Path | Mapping, what: str) -> dict:
    data = load_yaml(Path(source)) if isinstance(source, (str, Path)) else source
    if not isinstance(data, dict):
        raise ConfigError(f'{source}: {what} must be a mapping')
    return dict(data)


def load_project(config_dir: Path | str | None = None, scenario_override: Path | str | None = None,
                 overrides: Sequence[Path | Mapping] = ()) -> ProjectConfig:
    """Load and validate every file of a config directory.

    ``scenario_override``: a YAML merged over scenario.yaml (a scenario variant).
    ``overrides``: YAML files or dicts keyed by config file name (``{env: {...}, training: {...}}``)
    merged over the files, in order (the ablation steps use this)."""
    directory = Path(config_dir) if config_dir else default_config_dir()
    raw = {name: load_yaml(directory / f'{name}.yaml') for name in CONFIG_FILES}
    sources = {name: directory / f'{name}.yaml' for name in CONFIG_FILES}
    extra = [(scenario_override, {'scenario': _as_mapping(scenario_override, 'a scenario override')})] \
        if scenario_override else []
    extra += [(source, _as_mapping(source, 'an override')) for source in overrides]
    for source, data in extra:
        for name, values in data.items():
            if name not in CONFIG_FILES:
                raise ConfigError(f'{source}: unknown config file {name!r}; known: {", ".join(CONFIG_FILES)}')
            if not isinstance(raw[name], dict) or not isinstance(values, dict):
                raise ConfigError(f'{source}: {name} must be a mapping')
            raw[name] = deep_merge(raw[name], values)
            sources[name] = Path(str(source)) if isinstance(source, (str, Path)) else sources[name]
    parsed = {name: parse(schema, raw[name], sources[name]) for name, schema in CONFIG_FILES.items()}
    config = ProjectConfig(scenario=parsed['scenario'], graph=parsed['graph'], env=parsed['env'],
                           modes=parsed['modes'].modes, mode_matrix=parsed['modes'].matrix,
                           rewards=parsed['reward'].variants,
                           training=parsed['training'])
    config.mode(config.env.mode)
    config.reward(config.env.reward_variant)
    for name in config.mode_matrix.modes:
        if name not in config.modes:
            raise ConfigError(f'{sources["modes"]}: matrix: unknown mode {name!r}; known modes: {", ".join(config.modes)}')
    for method, settings in config.training.methods.items():
        for key, values in (('training', settings.training),
                            ('published.training', settings.published.training if settings.published else {})):
            if 'methods' in values:
                raise ConfigError(f'{sources["training"]}: methods.{method}.{key}: may not hold methods')
    for method in config.training.method_names:
        learns_from = config.training.method(method).reward_variant
        if learns_from is not None and learns_from not in config.rewards:
            key = (f'{method.removesuffix(PUBLISHED_SUFFIX)}.published' if method not in config.training.methods
                   else method)
            raise ConfigError(f'{sources["training"]}: methods.{key}.reward_variant: unknown {learns_from!r}; '
                              f'known: {", ".join(config.rewards)}')
        try:
            config.training.of_method(method)
        except ConfigError as error:
            raise ConfigError(f'{sources["training"]}: {error}') from None
    for key in ('modes', 'validation_modes'):
        for name in getattr(config.training.conditioning, key):
            if name not in config.modes:
                raise ConfigError(f'{sources["training"]}: conditioning.{key}: unknown mode {name!r}; '
                                  f'known modes: {", ".join(config.modes)}')
    return config


CellName = Annotated[str, StringConstraints(pattern=r'^[A-Za-z0-9_.-]+$')]   # a directory name


class VariantsFile(BaseModel):
    """config/variants.yaml: the scenario cells of the sweeps, each an override of scenario.yaml."""
    model_config = ConfigDict(extra='forbid', frozen=True)
    cells: dict[CellName, dict]


def load_variants(path: Path, config_dir: Path | None = None, overrides: Sequence = (),
                  only: Sequence[str] = ()) -> dict[str, ProjectConfig]:
    """The project config of each cell of a variants file (or of the cells named in ``only``);
    errors name the file and the cell."""
    variants = parse(VariantsFile, load_yaml(path), path).cells
    unknown = [name for name in only if name not in variants]
    if unknown:
        raise ConfigError(f'{path}: no cell {", ".join(map(repr, unknown))}; cells: {", ".join(variants)}')
    configs = {}
    for name in only or variants:
        try:
            configs[name] = load_project(config_dir, variants[name], overrides)
        except ConfigError as error:
            raise ConfigError(f'{path}: cells.{name} (merged over scenario.yaml): {error}') from None
    return configs
