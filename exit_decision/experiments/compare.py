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
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, StringConstraints
from tqdm import tqdm

from exit_decision.actions import ActionGrid
from exit_decision.config import ConfigError, ProjectConfig, default_config_dir, load_project, load_yaml, parse
from exit_decision.errors import UsageError
from exit_decision.evaluation.evaluate import EvaluatedRun, EvaluationResult, evaluate_policy
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.evaluation.report import (REFERENCE_DRIVERS, comparison_markdown, driver_runs, paired_comparison,
                                             write_run)
from exit_decision.tables import read_rows

CellName = Annotated[str, StringConstraints(pattern=r'^[A-Za-z0-9_.-]+$')]   # a directory name


class VariantsFile(BaseModel):
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


def plan_cells(methods: Sequence[str], configs: dict[str, ProjectConfig], modes: Sequence[str]) -> list[Cell]:
    """The cells of the sweep over the variants of ``configs``; a method is a reference driver
    or a policy.pt file (checked here against the graph and actions, which no variant changes)."""
    from exit_decision.policy import load_policy

    cells, names = [], set()
    for method in methods:
        if method in REFERENCE_DRIVERS:
            name, policy, per_mode = method, None, [tuple(modes)]
        elif Path(method).suffix == '.pt':
            policy = load_policy(method)
            config = next(iter(configs.values()))
            policy.check_compatible(config.graph.max_vehicles, config.graph.feature_set, config.env.decision_interval,
                                    ActionGrid(config.env.actions))
            name = f'{policy.metadata["algorithm"]}_{policy.metadata["mode"]}'
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
    from exit_decision.policy import load_policy

    if cell.policy is None:
        return driver_runs(config, cell.method, cell.modes, seeds)
    env = ExitDecisionEnv(config, mode=cell.modes[0])
    try:
        return evaluate_policy(env, load_policy(cell.policy), cell.modes, seeds)
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

    def summary(self) -> str:
        line = (f'{self.cells} cells: {self.done} run now, {self.skipped} already done (skipped), '
                f'{len(self.failed)} failed')
        return '\n'.join([line] + [f'  failed: {name}: {error}' for name, error in self.failed.items()])


def start_ray(address: str | None, workers: int, package_root: Path) -> None:
    """Connect to a Ray cluster at ``address``, or start a local one of ``workers`` CPUs that
    listens on loopback only (no dashboard, no usage report)."""
    if address is None:
        # read by ray at import: a single-node Ray whose servers bind 127.0.0.1 (with _node_ip_address)
        os.environ['RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'] = '0'
        os.environ['RAY_USAGE_STATS_ENABLED'] = '0'
    import ray

    if address is None:
        # workers import this same copy of the package (a source tree before its install)
        path = os.pathsep.join(filter(None, [str(package_root), os.environ.get('PYTHONPATH', '')]))
        ray.init(address=None, num_cpus=workers, include_dashboard=False, log_to_driver=False,
                 _node_ip_address='127.0.0.1', runtime_env={'env_vars': {'PYTHONPATH': path}})
    else:
        ray.init(address=address, log_to_driver=False)


def _error_text(error: Exception) -> str:
    cause = getattr(error, 'cause', None) or error
    return re.sub(r'\s+', ' ', f'{type(cause).__name__}: {cause}').strip()[:300]


def run_sweep(cells: Sequence[Cell], configs: dict[str, ProjectConfig], seeds: Sequence[int], out_dir: Path,
              address: str | None = None, workers: int | None = None, retries: int = 2,
              progress: bool = True) -> SweepResult:
    """Run every cell not done yet (on these seeds) in ``out_dir`` as a Ray task (one simulation per worker
    process), writing each cell's files as it finishes; ``retries``: further attempts of a
    cell whose task raised or whose worker died."""
    result = SweepResult(cells=len(cells))
    pending = [cell for cell in cells if not cell.done(out_dir, seeds)]
    result.skipped = len(cells) - len(pending)
    if not pending:
        return result
    import exit_decision
    start_ray(address, workers or os.cpu_count() or 1, Path(exit_decision.__file__).resolve().parent.parent)
    import ray
    try:
        remote = ray.remote(num_cpus=1, max_calls=1, max_retries=retries, retry_exceptions=True)(run_cell)
        started = time.perf_counter()
        futures = {remote.remote(cell, configs[cell.variant], list(seeds)): cell for cell in pending}
        with tqdm(total=len(cells), initial=result.skipped, desc='cells', unit='cell', disable=not progress) as bar:
            while futures:
                ready, _ = ray.wait(list(futures), num_returns=1)
                cell = futures.pop(ready[0])
                try:
                    runs = ray.get(ready[0])
                except ray.exceptions.RayError as error:
                    result.failed[cell.name] = _error_text(error)
                    bar.write(f'failed after {retries + 1} attempt(s): {cell.name}: {result.failed[cell.name]}')
                else:
                    write_cell(out_dir, cell, runs, ActionGrid(configs[cell.variant].env.actions))
                    result.done += 1
                bar.update()
        result.seconds = time.perf_counter() - started
    finally:
        ray.shutdown()
    return result


def write_summary(out_dir: Path, cells: Sequence[Cell], configs: dict[str, ProjectConfig], modes: Sequence[str],
                  command: str) -> Path:
    """``<out>/summary.md``: per variant, mean ± std of each finished run and each run against
    the neutral teacher (paired over seeds), read back from the CSVs."""
    sections = [(f'# Comparison sweep\n\nMade by `{command}`; per variant: mean ± std over episodes, then each '
                 f'run minus the teacher on the same seeds (95% intervals).')]
    for variant, config in configs.items():
        runs = [EvaluatedRun(path.stem, [{k: float(v) for k, v in row.items()} for row in read_rows(path)],
                             EvaluationResult())
                for cell in cells if cell.variant == variant for path in cell.files(out_dir) if path.is_file()]
        if not runs:
            continue
        sections.append(f'## {variant}\n\n' + markdown_table([(run.label, summarize(run.episodes)) for run in runs]))
        paired = paired_comparison(runs, modes, config.scenario.max_steps)
        if paired:
            sections.append(comparison_markdown(paired))
    path = out_dir / 'summary.md'
    path.write_text('\n\n'.join(sections) + '\n', encoding='utf-8')
    return path


def default_methods() -> list[str]:
    """The reference drivers and the shipped mode-conditioned policy."""
    return [*REFERENCE_DRIVERS, str(default_config_dir().parent / 'policies' / 'mdgqn_conditioned' / 'policy.pt')]
