"""The comparison sweep: every method on every scenario variant, on the same seeds, as Ray tasks.

Variants are the cells of ``config/variants.yaml``, each a scenario override merged over
scenario.yaml. A *cell* is one method on one variant: a reference driver (``rule_based``,
``sumo``) or a per-mode policy plays the seeds once and is scored under every mode; a
mode-conditioned policy acts differently per mode, so each of its modes is a cell of its own.
A cell is one Ray task that builds its own ``ExitDecisionEnv`` and runs the evaluation of
``exit_decision.evaluation`` (``driver_runs``, ``evaluate_policy``); the task runs with
``max_calls=1``, so its worker process exits after it and no process ever holds two libsumo
simulations. Results are written by the driver as each cell finishes, as
``<out>/<variant>/<run>.csv`` (the files of ``evaluate``); a cell whose files all exist (with
the same seeds) is skipped, a failed one is retried by Ray and, if it still fails, reported without losing the
others.

A learned method's training run is kept outside the results, in ``<policies>/<run>/`` (its
policy.pt beside the config.json and timing.json that tell it done; ``policies/comparison`` by
default), and reused when done; the logs the page reads (``LOG_FILES``) are copied to
``<out>/training/<run>/``, so the page is rebuilt from ``<out>`` alone, without a checkpoint.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from tqdm import tqdm

from exit_decision.actions import ActionGrid
from exit_decision.config import ConfigError, ProjectConfig, TrainingConfig, deep_merge, load_yaml, parse
from exit_decision.errors import UsageError
from exit_decision.learning.actors import start_ray
from exit_decision.evaluation.evaluate import EvaluatedRun, evaluate_policy
from exit_decision.evaluation.report import REFERENCE_DRIVERS, driver_runs, write_run
from exit_decision.model.names import GRID_ALGORITHM, default_policy_dir, policy_path
from exit_decision.tables import read_rows

@dataclass(frozen=True)
class Cell:
    """One method on one variant, scored under ``modes``."""
    method: str                  # rule_based, sumo, or a policy's <algorithm>_<mode>
    variant: str
    modes: tuple[str, ...]
    policy: Path | None = None   # a learned method's policy.pt

    @property
    def name(self) -> str:
        at = f' at {self.modes[0]}' if self.policy and len(self.modes) == 1 else ''
        return f'{self.method} on {self.variant}{at}'

    def files(self, out_dir: Path) -> list[Path]:
        return [out_dir / self.variant / f'{self.method}_{mode}.csv' for mode in self.modes]

    def done(self, out_dir: Path, seeds: Sequence[int]) -> bool:
        """Every file of the cell is there, with these seeds (other seeds: run it again)."""
        return all(path.is_file() and [int(row['seed']) for row in read_rows(path)] == list(seeds)
                   for path in self.files(out_dir))


def plan_cells(methods: Sequence[str], configs: dict[str, ProjectConfig], modes: Sequence[str],
               trained: dict[str, Path] | None = None) -> list[Cell]:
    """The cells of the sweep over the variants of ``configs``; a method is a reference driver
    or a policy.pt file (checked here against the graph and actions, which no variant changes);
    ``trained``: policies named by their training run (``<method>_s<seed>``)."""
    from exit_decision.model.policy import load_policy

    cells, names = [], set()
    for method, run_name in [*((m, None) for m in methods), *((str(path), name) for name, path in (trained or {}).items())]:
        if method in REFERENCE_DRIVERS:
            name, policy, per_mode = method, None, [tuple(modes)]
        elif Path(method).suffix == '.pt':
            policy = load_policy(method)
            policy.check_compatible(next(iter(configs.values())))
            name = run_name or policy.run_name
            per_mode = [(mode,) for mode in modes] if policy.conditioned else [tuple(modes)]
            policy = Path(method)
        else:
            raise UsageError(f'--method {method!r}: expected {", ".join(REFERENCE_DRIVERS)} or a policy.pt file')
        if name in names:
            raise UsageError(f'--method {method!r}: a second method named {name!r}')
        names.add(name)
        cells += [Cell(name, variant, scored, policy) for variant in configs for scored in per_mode]
    return cells


def run_cell(cell: Cell, config: ProjectConfig, seeds: Sequence[int]) -> list[EvaluatedRun]:
    """One cell in this process (a Ray worker that runs nothing else)."""
    from exit_decision.env import ExitDecisionEnv

    if cell.policy is None:
        return driver_runs(config, cell.method, cell.modes, seeds)
    env = ExitDecisionEnv(config, mode=cell.modes[0])
    try:
        return evaluate_policy(env, cell.policy, cell.modes, seeds, name=cell.method)
    finally:
        env.close()


def write_cell(out_dir: Path, cell: Cell, runs: Sequence[EvaluatedRun], grid: ActionGrid) -> None:
    """The cell's files, each moved into place whole: a cell is done when all of them exist."""
    target = out_dir / cell.variant
    target.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix='.cell-', dir=target))
    marks = {path.name for path in cell.files(out_dir)}
    try:
        for run in runs:
            write_run(staging, run, grid)
        for path in sorted(staging.iterdir(), key=lambda path: path.name in marks):
            os.replace(path, target / path.name)   # the episode CSVs, which mark the cell done, last
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@dataclass
class SweepResult:
    cells: int = 0
    skipped: int = 0
    done: int = 0
    failed: dict[str, str] = field(default_factory=dict)   # cell name -> error
    seconds: float = 0.0                                   # from the first task to the last result
    unit: str = 'cells'

    def summary(self) -> str:
        line = (f'{self.cells} {self.unit}: {self.done} run now, {self.skipped} already done (skipped), '
                f'{len(self.failed)} failed')
        return '\n'.join([line] + [f'  failed: {name}: {error}' for name, error in self.failed.items()])


def _error_text(error: Exception) -> str:
    cause = getattr(error, 'cause', None) or error
    return re.sub(r'\s+', ' ', f'{type(cause).__name__}: {cause}').strip()[:300]


@dataclass(frozen=True)
class Job:
    """One Ray task: ``function(*args)`` in a fresh worker process; ``done(result)`` in the driver."""
    name: str
    function: Callable
    args: tuple
    done: Callable[[Any], None]


def run_on_ray(jobs: Sequence[Job], result: SweepResult, address: str | None, workers: int | None, retries: int,
               progress: bool) -> SweepResult:
    """Run the jobs as Ray tasks (``max_calls=1``: one simulation per worker process), each
    ``done`` as its task finishes; ``retries``: further attempts of a task that raised or whose
    worker died; failures are recorded in ``result`` without stopping the others."""
    if not jobs:
        return result
    import exit_decision
    start_ray(address, workers or os.cpu_count() or 1, Path(exit_decision.__file__).resolve().parent.parent)
    import ray
    try:
        started = time.perf_counter()
        futures = {ray.remote(num_cpus=1, max_calls=1, max_retries=retries, retry_exceptions=True)(job.function)
                   .remote(*job.args): job for job in jobs}
        with tqdm(total=result.cells, initial=result.skipped, desc=result.unit, unit='task', disable=not progress) as bar:
            while futures:
                ready, _ = ray.wait(list(futures), num_returns=1)
                job = futures.pop(ready[0])
                try:
                    value = ray.get(ready[0])
                except ray.exceptions.RayError as error:
                    result.failed[job.name] = _error_text(error)
                    bar.write(f'failed after {retries + 1} attempt(s): {job.name}: {result.failed[job.name]}')
                else:
                    job.done(value)
                    result.done += 1
                bar.update()
        result.seconds = time.perf_counter() - started
    finally:
        ray.shutdown()
    return result


def run_sweep(cells: Sequence[Cell], configs: dict[str, ProjectConfig], seeds: Sequence[int], out_dir: Path,
              address: str | None = None, workers: int | None = None, retries: int = 2,
              progress: bool = True) -> SweepResult:
    """Run every cell not done yet (on these seeds) in ``out_dir``, writing each cell's files as
    it finishes."""
    pending = [cell for cell in cells if not cell.done(out_dir, seeds)]
    result = SweepResult(cells=len(cells), skipped=len(cells) - len(pending))
    jobs = [Job(cell.name, run_cell, (cell, configs[cell.variant], list(seeds)),
                partial(write_cell, out_dir, cell, grid=ActionGrid(configs[cell.variant].env.actions)))
            for cell in pending]
    return run_on_ray(jobs, result, address, workers, retries, progress)


# --- training the learned methods ---------------------------------------------------------------

class ComparisonTraining(BaseModel):
    """``config/comparison.yaml``: how ``compare`` trains the learned methods."""
    model_config = ConfigDict(extra='forbid', frozen=True)
    training_mode: str
    seeds: Annotated[list[int], Field(min_length=1)]
    budget: dict     # merged over training.yaml for every method alike (before the method's own settings)


@dataclass(frozen=True)
class TrainingRun:
    """One learned method trained with one seed on the base scenario."""
    method: str
    seed: int
    mode: str

    @property
    def name(self) -> str:
        return f'{self.method}_s{self.seed}'

    def directory(self, policies_dir: Path) -> Path:
        """Where the run trains and keeps its policy.pt (with its last.pt and candidates, ignored by git)."""
        return policies_dir / self.name

    def log_directory(self, out_dir: Path) -> Path:
        """Where the results keep the run's logs (LOG_FILES), which the page reads."""
        return out_dir / 'training' / self.name

    def done(self, policies_dir: Path, config: ProjectConfig) -> bool:
        """Trained, its policy.pt kept, with the settings this method depends on (another budget
        or setting: train again)."""
        directory = self.directory(policies_dir)
        return (directory / 'policy.pt').is_file() and finished(directory, config, self.method)

    def logged(self, out_dir: Path) -> bool:
        """The results hold the logs of a finished run (timing.json, the trainer's last file): the
        page rebuilt from them counts it, whatever config it was trained under (no checkpoint
        read; its CSVs are the results of that run)."""
        return (self.log_directory(out_dir) / 'timing.json').is_file()


#: a training run's files the comparison page reads (copied beside the results, small)
LOG_FILES = ('config.json', 'timing.json', 'training.csv', 'validation.csv')


def finished(directory: Path, config: ProjectConfig, method: str) -> bool:
    """A run directory of a finished training (timing.json is the trainer's last file: an
    interrupted run has none) with the settings ``method`` depends on under ``config``."""
    if not ((directory / 'timing.json').is_file() and (directory / 'config.json').is_file()):
        return False
    recorded = json.loads((directory / 'config.json').read_text())
    try:
        then = ProjectConfig.model_validate(recorded['config'])
        return (recorded['episodes'], run_settings(then, method)) == (
            config.training.episodes, run_settings(config, method))
    except (ValidationError, ConfigError, KeyError):   # a config of another release, or without this method
        return False


def run_settings(config: ProjectConfig, method: str) -> dict:
    """What a training run of ``method`` depends on: the scenario, graph, env and modes, the
    rewards it learns and is scored with, its merged training settings and its own; another
    method's settings or an unused reward variant do not count."""
    settings = config.training.method(method)
    rewards = sorted({config.env.reward_variant, settings.reward_variant or config.env.reward_variant})
    return json.loads(json.dumps({
        'scenario': config.scenario.model_dump(), 'graph': config.graph.model_dump(), 'env': config.env.model_dump(),
        'modes': {name: mode.model_dump() for name, mode in config.modes.items()},
        'rewards': {name: config.reward(name).model_dump() for name in rewards},
        'training': config.training.of_method(method).model_dump(exclude={'methods'}),
        'method': settings.model_dump(exclude={'published'})}))


def load_comparison_training(path: Path, config: ProjectConfig,
                             methods: Sequence[str]) -> tuple[list[TrainingRun], ProjectConfig, dict]:
    """The training runs of ``methods``, the base config under the stated budget, the budget."""
    settings = parse(ComparisonTraining, load_yaml(path), path)
    try:
        config.mode(settings.training_mode)
        training = parse(TrainingConfig, deep_merge(config.training.model_dump(), settings.budget), 'budget')
        budgeted = config.model_copy(update={'training': training})
        for method in methods:
            budgeted.training.of_method(method)
    except ConfigError as error:
        raise ConfigError(f'{path}: {error}') from None
    runs = [TrainingRun(method, seed, settings.training_mode) for method in methods for seed in settings.seeds]
    return runs, budgeted, settings.budget


def run_training(run: TrainingRun, config: ProjectConfig, directory: Path) -> str:
    """(A Ray task) train one method with one seed from scratch; the kept policy.pt's path."""
    from exit_decision.learning.trainer import Trainer

    shutil.rmtree(directory, ignore_errors=True)   # an interrupted run starts afresh
    return str(Trainer(config, run.method, run.mode, run.seed, directory).run(config.training.episodes, progress=False))


def publish_logs(run: TrainingRun, policies_dir: Path, out_dir: Path) -> None:
    """Copy the run's logs the page reads from its training directory to the results."""
    target = run.log_directory(out_dir)
    target.mkdir(parents=True, exist_ok=True)
    for name in LOG_FILES:
        if (run.directory(policies_dir) / name).is_file():
            shutil.copyfile(run.directory(policies_dir) / name, target / name)


def run_trainings(runs: Sequence[TrainingRun], config: ProjectConfig, policies_dir: Path, out_dir: Path,
                  address: str | None = None, workers: int | None = None, retries: int = 2,
                  progress: bool = True) -> SweepResult:
    """Train every run not done yet in ``policies_dir``, one Ray task each (a rerun reuses
    finished runs); every done run's logs are copied to ``out_dir``."""
    pending = [run for run in runs if not run.done(policies_dir, config)]
    result = SweepResult(cells=len(runs), skipped=len(runs) - len(pending), unit='training runs')
    jobs = [Job(run.name, run_training, (run, config, run.directory(policies_dir)), lambda _: None)
            for run in pending]
    run_on_ray(jobs, result, address, workers, retries, progress)
    for run in runs:
        if run.done(policies_dir, config):
            publish_logs(run, policies_dir, out_dir)
    return result


def default_methods() -> list[str]:
    """The reference drivers and the shipped mode-conditioned policy on the grid (the sweep's
    pages were made with it)."""
    return [*REFERENCE_DRIVERS, str(policy_path(default_policy_dir(), GRID_ALGORITHM))]
