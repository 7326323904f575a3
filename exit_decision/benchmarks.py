"""Benchmark commands of the core: figures printed, never asserted in tests (the ROS stack's
benchmark, ``bench ros``, is ``exit_decision.ros.stack.bench``)."""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from exit_decision.config import ProjectConfig
from exit_decision.scenario.simulation import Backend, HighwaySimulation


def simulation_throughput(config: ProjectConfig, backend: Backend, episodes: int, seed: int) -> dict[str, float]:
    """Full-state steps of the scenario (SUMO drives the CAVs, states read every step)."""
    steps = vehicle_steps = 0
    with HighwaySimulation(config.scenario, cav_driver='sumo', backend=backend) as sim:
        started = time.perf_counter()
        for episode in range(episodes):
            result = sim.reset(seed + episode)
            while not (result.terminated or result.truncated):
                result = sim.step()
                steps += 1
                vehicle_steps += len(result.vehicles)
        elapsed = time.perf_counter() - started
    return {'steps': steps, 'seconds': elapsed, 'steps_per_s': steps / elapsed,
            'vehicle_steps_per_s': vehicle_steps / elapsed}


def bench_simulation(config: ProjectConfig, episodes: int, seed: int) -> str:
    rows = {backend: simulation_throughput(config, backend, episodes, seed)
            for backend in ('libsumo', 'traci')}
    lines = [f'simulation throughput, {episodes} episode(s) from seed {seed} '
             f'(SUMO-driven CAVs, full state read every step)',
             f'{"backend":<8} {"steps":>7} {"seconds":>8} {"steps/s":>9} {"vehicle-steps/s":>16}']
    for backend, row in rows.items():
        lines.append(f'{backend:<8} {row["steps"]:>7} {row["seconds"]:>8.2f} {row["steps_per_s"]:>9.0f} '
                     f'{row["vehicle_steps_per_s"]:>16.0f}')
    ratio = rows['libsumo']['steps_per_s'] / rows['traci']['steps_per_s']
    lines.append(f'libsumo / TraCI speed ratio: {ratio:.1f}x')
    return '\n'.join(lines)


#: the recipes ``bench learning`` measures: (label, algorithm, action space, override file under config/)
LEARNING_RECIPES = (('the grid\'s conditioned MDGQN (demonstrations)', 'mdgqn', 'grid', None),
                    ('the conditioned MDGQN over options, no demonstrations (Q-learning)', 'mdgqn', 'options',
                     'overrides/options_no_demonstrations.yaml'),
                    ('the conditioned MDGQN over options, one step over the prior', 'mdgqn', 'options',
                     'overrides/options_prior.yaml'))


#: the recipe ``bench learning --actors`` trains: the shipped policy's (mdgqn_options_conditioned)
ACTOR_RECIPE = LEARNING_RECIPES[1]


def recipe_config(config_dir: Path | None, scenario_override, overrides, recipe: tuple) -> ProjectConfig:
    """The config of a recipe of ``LEARNING_RECIPES``: its override file over the given ones."""
    from exit_decision.config import default_config_dir, load_project
    override = recipe[3]
    extra = [(config_dir or default_config_dir()) / override] if override else []
    return load_project(config_dir, scenario_override, [*overrides, *extra])


def bench_learning(config_dir: Path | None, scenario_override, overrides, seed: int, episodes: int = 2) -> str:
    """Per recipe (``LEARNING_RECIPES``): an episode's time without and with learning and their
    ratio, the updates per episode (``updates_per_decision`` per decision: the ratio is not bought
    by updating less), the time of one gradient update, and one greedy forward."""
    lines = [f'learning benchmark ({episodes} episode(s) each way, torch threads: 1, one process)',
             f'{"recipe":<74} {"update [ms]":>11} {"episode [s]":>11} {"+learning [s]":>13} {"ratio":>6} '
             f'{"updates/ep":>10}']
    for recipe in LEARNING_RECIPES:
        label, algorithm, action_space, _ = recipe
        config = recipe_config(config_dir, scenario_override, overrides, recipe)
        figures = _learning_figures(config, algorithm, action_space, seed, episodes)
        lines.append(f'{label:<74} {figures["update_ms"]:>11.2f} {figures["without"]:>11.2f} {figures["with"]:>13.2f} '
                     f'{figures["with"] / figures["without"]:>5.1f}x {figures["updates_per_episode"]:>10.0f}')
        lines.append(f'  batch {figures["batch"]}, {figures["decisions_per_episode"]:.0f} decisions per episode; '
                     f'greedy forward, all {config.graph.max_vehicles} rows CAVs: median {figures["forward_ms"]:.3f} ms')
        lines.append('  where an update goes [ms]: ' + ', '.join(f'{part} {ms:.2f}' for part, ms in figures['parts'].items()))
    return '\n'.join(lines)


def _learning_figures(config, algorithm: str, action_space: str, seed: int, episodes: int) -> dict[str, float]:
    import tempfile

    import numpy as np

    from exit_decision.graph import TrafficGraph
    from exit_decision.learning.trainer import Trainer
    from exit_decision.learning.validation import validation_seeds
    from exit_decision.model.names import CONDITIONED
    from exit_decision.model.policy import q_values

    training = config.training.model_copy(update={
        'warmup_decisions': 0, 'validation': config.training.validation.model_copy(update={'every_episodes': 10 ** 6})})
    config = config.model_copy(update={'training': training})
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, algorithm, CONDITIONED, seed, Path(tmp), action_space)
        t = trainer.training
        if 'prior' in (t.bootstrap, t.exploration.around):   # measured on two seeds (untimed)
            trainer.use_prior(validation_seeds(2), progress=False)
        for transition in trainer.collector.episode(seed, trainer.agent.online, trainer.episode_mode(), 0.1):
            trainer.experience.add(transition)   # a replay to sample from (untimed)
        for label, updates in (('without', 0), ('with', t.updates_per_decision)):
            counted = {'decisions': 0, 'updates': 0}

            def learn(transitions: list, updates: int = updates) -> None:
                for transition in transitions:
                    trainer.experience.add(transition)
                counted['decisions'] += 1
                for _ in range(updates):
                    trainer.learn_step()
                    counted['updates'] += 1
            started = time.perf_counter()
            for episode in range(episodes):
                trainer.collector.episode(seed + 1 + episode, trainer.agent.online, trainer.episode_mode(), 0.1,
                                          on_decision=learn)
            figures[label] = (time.perf_counter() - started) / episodes
            if updates:
                figures['updates_per_episode'] = counted['updates'] / episodes
                figures['decisions_per_episode'] = counted['decisions'] / episodes
        sampled = trainer.experience.sample()
        for _ in range(10):
            trainer.agent.update(sampled.arrays, sampled.is_demo, 1.0)
        count, started = 200, time.perf_counter()
        for _ in range(count):
            trainer.agent.update(sampled.arrays, sampled.is_demo, 1.0)
        figures['update_ms'] = (time.perf_counter() - started) / count * 1000
        figures['parts'] = _update_parts(trainer)
        figures['batch'] = t.batch_size
        n, f = config.graph.max_vehicles, trainer.shape.num_features
        rng = np.random.default_rng(seed)
        graph = TrafficGraph(rng.random((n, f), dtype=np.float32), np.ones((n, n), np.uint8),
                             np.ones(n, bool), tuple(f'CAV_{i}' for i in range(n)))
        network = trainer.agent.online.eval()
        samples = []
        for _ in range(500):
            started = time.perf_counter()
            q_values(network, graph, np.full(6, 0.25))
            samples.append((time.perf_counter() - started) * 1000)
        figures['forward_ms'] = float(np.median(samples[50:]))
        trainer.env.close()
    return figures


def _update_parts(trainer, count: int = 100) -> dict[str, float]:
    """Mean milliseconds of each part of one gradient update, timed apart: sampling the batch
    (replay, relabelling, scoring), the online forward on the batch's states, the bootstrap
    targets (the target network's forward on the next states and, for double Q-learning, the
    online one's), the backward pass, and the optimiser's step with clipping and the soft update."""
    import torch
    from torch import nn

    from exit_decision.model.networks import SelectedRows

    agent = trainer.agent
    parts = dict.fromkeys(('sample', 'forward', 'targets', 'backward', 'step'), 0.0)
    for _ in range(count):
        started = time.perf_counter()
        sampled = trainer.experience.sample()
        batch = {key: torch.from_numpy(value) for key, value in sampled.arrays.items()}
        marks = [time.perf_counter()]
        rows = torch.nonzero(batch['actions'] >= 0)
        selected = SelectedRows.of(batch['adjacency'], rows, batch['degrees'])
        q = agent.online.cav_q_values(batch['features'], selected, batch.get('weights'))
        marks.append(time.perf_counter())
        with torch.no_grad():
            targets = agent.td_targets(batch, rows)
        marks.append(time.perf_counter())
        taken = q.gather(1, selected.at(batch['actions']).unsqueeze(1)).squeeze(1)
        loss = nn.functional.smooth_l1_loss(taken, targets)
        agent.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        marks.append(time.perf_counter())
        nn.utils.clip_grad_norm_(agent.online.parameters(), agent.settings.gradient_clip)
        agent.optimizer.step()
        agent.soft_update()
        marks.append(time.perf_counter())
        for part, (begin, end) in zip(parts, zip([started, *marks[:-1]], marks)):
            parts[part] += (end - begin) * 1000 / count
    return parts


@dataclass(frozen=True)
class Collected:
    """A timed run of training episodes: its ``decisions`` and ``updates`` in ``seconds`` of
    episodes, after ``start`` seconds of getting its collectors up (Ray and the actors, their
    simulations made; 0 in this process)."""
    decisions: int
    updates: int
    seconds: float
    start: float = 0.0

    @property
    def wall(self) -> float:
        return self.start + self.seconds

    def per_second(self, count: int) -> float:
        return count / self.seconds if self.seconds > 0 else float('nan')


def bench_actors(config_dir: Path | None, scenario_override, overrides, seed: int, actors: list[int],
                 episodes: int) -> str:
    """``bench learning --actors``: the shipped recipe (``ACTOR_RECIPE``) trained for ``episodes``
    episodes with each number of ``actors`` (0: in this process; the trainer's own loops, without
    validation or checkpoints), then, with updates off, collected by each number of actors and by
    as many plain processes without Ray (the ceiling of the scaling); ``actor_table``."""
    label, algorithm, action_space, _ = ACTOR_RECIPE
    config = recipe_config(config_dir, scenario_override, overrides, ACTOR_RECIPE)
    counts = sorted(set(actors))
    t = config.training.of_method(algorithm)
    prior = _measured_prior(config, algorithm, action_space, seed) if 'prior' in (t.bootstrap, t.exploration.around) \
        else None
    run = (algorithm, action_space, seed, episodes, prior)
    learning = {count: timed_episodes(config, *run, actors=count) for count in counts}
    alone = config.model_copy(update={'training': config.training.model_copy(update={'updates_per_decision': 0})})
    collecting = {count: timed_episodes(alone, *run, actors=count) for count in counts}
    plain = {count: plain_processes(alone, *run, count=count) for count in counts if count}
    return actor_table(f'{label}, updates_per_decision {t.updates_per_decision}',
                       episodes, learning, collecting, plain)


def _measured_prior(config: ProjectConfig, algorithm: str, action_space: str, seed: int):
    """The prior over options (``Trainer.use_prior``) on two validation seeds, measured once for
    every run of ``bench_actors`` (untimed)."""
    import tempfile

    from exit_decision.learning.trainer import Trainer
    from exit_decision.learning.validation import validation_seeds
    from exit_decision.model.names import CONDITIONED
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, algorithm, CONDITIONED, seed, Path(tmp), action_space)
        trainer.use_prior(validation_seeds(2), progress=False)
        trainer.env.close()
    return trainer.collector.prior


def timed_episodes(config: ProjectConfig, algorithm: str, action_space: str, seed: int, episodes: int, prior,
                   actors: int = 0, barrier=None) -> Collected:
    """``episodes`` training episodes of a new conditioned run (``prior``: the measured prior, or
    None), by the trainer's own loop: in this process (``actors`` 0: ``Trainer.episodes_here``)
    or on that many actors of a local Ray (``Trainer.episodes_on_actors``), timed from when every
    actor is up; ``barrier``: waited on just before (plain processes start together)."""
    import tempfile

    from exit_decision.learning.trainer import Trainer
    from exit_decision.model.names import CONDITIONED
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, algorithm, CONDITIONED, seed, Path(tmp), action_space)
        try:
            if prior is not None:
                trainer.set_prior(prior)
            started = time.perf_counter()
            if actors:
                pool = trainer.actor_pool(actors, None)
                pool.pids()   # answers once every actor is made (its simulation too)
                source = trainer.episodes_on_actors(episodes, pool)
            else:
                source = trainer.episodes_here(episodes)
            if barrier is not None:
                barrier.wait(timeout=600)
            ready = time.perf_counter()
            for _ in source:
                pass
            finished = time.perf_counter()
        finally:
            trainer.env.close()
    return Collected(trainer.state.decisions, trainer.state.updates, finished - ready, ready - started)


def plain_processes(config: ProjectConfig, algorithm: str, action_space: str, seed: int, episodes: int, prior,
                    count: int) -> Collected:
    """``count`` processes without Ray (``timed_episodes`` in this process's way), each on its own
    seed and the ``count``-th part of ``episodes`` (rounded up), started together: their decisions
    over the longest one's seconds. Two libsumo simulations in two processes: the most two actors
    can collect on this machine."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    context = multiprocessing.get_context('spawn')
    each = -(-episodes // count)
    with context.Manager() as manager, ProcessPoolExecutor(count, mp_context=context) as pool:
        barrier = manager.Barrier(count)
        runs = [pool.submit(timed_episodes, config, algorithm, action_space, seed + index, each, prior, barrier=barrier)
                for index in range(count)]
        done = [run.result() for run in runs]
    return Collected(sum(run.decisions for run in done), 0, max(run.seconds for run in done))


def actor_table(recipe: str, episodes: int, learning: dict[int, Collected], collecting: dict[int, Collected],
                plain: dict[int, Collected]) -> str:
    """One table, a row per number of actors: with learning, the start, the wall time to
    ``episodes`` episodes, collected decisions/s and updates/s (over the episodes' seconds); with
    updates off (``collecting``), the decisions/s, the time a decision takes with learning over
    without (the cost of learning: target <= 2x) and, for actors >= 1, the decisions/s's ratio to 1
    actor's; as many plain processes' (``plain``) and their ratio to one's; then the 1 -> 2 line."""
    lines = [f'learning with actors: {recipe}; {episodes} training episode(s) per run (no validation, '
             f'no checkpoints), a local Ray on loopback, torch threads: 1',
             f'{"actors":>6} {"start [s]":>9} {"wall [s]":>8} {"decisions/s":>11} {"updates/s":>9} | '
             f'{"updates off: decisions/s":>24} {"learning cost":>13} {"x 1 actor":>9} | '
             f'{"plain processes: decisions/s":>28} '
             f'{"x 1 process":>11}']

    def decisions_per_s(figures: dict[int, Collected], count: int) -> float:
        return figures[count].per_second(figures[count].decisions)

    def ratio(figures: dict[int, Collected], count: int) -> str:
        if not count or count not in figures or 1 not in figures:
            return '-'
        return f'{decisions_per_s(figures, count) / decisions_per_s(figures, 1):.2f}x'

    def rate(figures: dict[int, Collected], count: int) -> str:
        return f'{decisions_per_s(figures, count):.0f}' if count in figures else '-'

    def cost(count: int) -> str:
        if count not in collecting:
            return '-'
        return f'{decisions_per_s(collecting, count) / decisions_per_s(learning, count):.2f}x'

    for count, run in learning.items():
        lines.append(f'{count:>6} {run.start:>9.1f} {run.wall:>8.1f} {rate(learning, count):>11} '
                     f'{run.per_second(run.updates):>9.1f} | {rate(collecting, count):>24} {cost(count):>13} '
                     f'{ratio(collecting, count):>9} | '
                     f'{rate(plain, count):>28} {ratio(plain, count):>11}')
    lines.append('start: Ray and the actors up (in the wall time); decisions/s, updates/s: over the episodes alone; '
                 'plain processes: that many processes without Ray, each its share of the episodes, started together; '
                 'learning cost: the time of a decision with learning over without (updates off), target <= 2x')
    if 2 in collecting and 1 in collecting:
        lines.append(f'scaling from 1 to 2 actors, updates off: {ratio(collecting, 2)}; the ceiling, two plain '
                     f'processes over one: {ratio(plain, 2)} (target >= 1.6x)')
    return '\n'.join(lines)


def bench_sweep(config_dir: Path | None, episodes: int, seed: int) -> str:
    """The compare sweep's throughput (rule_based on every variant, ``episodes`` seeds per cell)
    on a local Ray with 1 worker and with one per core; worker start-up counts, Ray's does not."""
    import os
    import tempfile

    from exit_decision.config import default_config_dir
    from exit_decision.config import load_variants
    from exit_decision.experiments.compare import plan_cells, run_sweep

    configs = load_variants((config_dir or default_config_dir()) / 'variants.yaml', config_dir)
    cells = plan_cells(['rule_based'], configs, [next(iter(configs.values())).env.mode])
    seeds = list(range(seed, seed + episodes))
    lines = [f'compare sweep, local Ray: rule_based on {len(cells)} variants x {episodes} seed(s), one process per cell']
    rates = {}
    for workers in sorted({1, os.cpu_count() or 1}):
        with tempfile.TemporaryDirectory() as out:
            result = run_sweep(cells, configs, seeds, Path(out), workers=workers, retries=0, progress=False)
        rates[workers] = len(cells) * episodes / result.seconds
        failed = f', {len(result.failed)} cell(s) failed' if result.failed else ''
        lines.append(f'  {workers} worker(s): {result.seconds:6.1f} s, {rates[workers]:.2f} episodes/s{failed}')
    lines.append(f'  {max(rates)} / 1 worker(s) throughput ratio: {rates[max(rates)] / rates[1]:.2f}x')
    return '\n'.join(lines)
