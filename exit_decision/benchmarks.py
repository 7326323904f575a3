"""Benchmark commands of the core: figures printed, never asserted in tests (the ROS stack's
benchmark, ``bench ros``, is ``exit_decision.ros.stack.bench``)."""
from __future__ import annotations

import time
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


def bench_learning(config: ProjectConfig, seed: int, episodes: int = 2) -> str:
    """Environment steps/s with and without learning, ms per update, inference latency."""
    import tempfile

    import numpy as np

    from exit_decision.graph import TrafficGraph
    from exit_decision.learning.trainer import Trainer
    from exit_decision.model.names import CONDITIONED
    from exit_decision.model.policy import q_values

    training = config.training.model_copy(update={
        'warmup_decisions': 0,
        'demonstrations': config.training.demonstrations.model_copy(update={'episodes': 1, 'pretrain_updates': 0}),
        'validation': config.training.validation.model_copy(update={'every_episodes': 10 ** 6})})
    config = config.model_copy(update={'training': training})
    lines = [f'learning benchmark, the mode-conditioned MDGQN ({episodes} episode(s) each, torch threads: 1)']
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, 'mdgqn', CONDITIONED, seed, Path(tmp))
        for transition in trainer.collector.episode(seed):
            trainer.experience.demos.add(transition)
        timings = {}
        for label, updates in (('without learning', 0), ('with learning', training.updates_per_decision)):
            def learn(transitions: list, updates: int = updates) -> None:
                for _ in range(updates):
                    trainer.learn_step()
            steps, started = 0, time.perf_counter()
            for episode in range(episodes):
                trainer.collector.episode(seed + episode, trainer.agent.online, trainer.episode_mode(), 0.1,
                                          on_decision=learn)
                steps += trainer.env.episode_log.steps
            elapsed = time.perf_counter() - started
            timings[label] = (steps / elapsed, elapsed / episodes)
            lines.append(f'  env steps/s {label:<17} {steps / elapsed:8.0f}   ({elapsed / episodes:.2f} s per episode)')
        sampled = trainer.experience.sample()
        for _ in range(10):
            trainer.agent.update(sampled.arrays, sampled.is_demo, 1.0)
        count, started = 200, time.perf_counter()
        for _ in range(count):
            trainer.agent.update(sampled.arrays, sampled.is_demo, 1.0)
        lines.append(f'  gradient update (batch {training.batch_size}): '
                     f'{(time.perf_counter() - started) / count * 1000:.2f} ms')
        n, f = config.graph.max_vehicles, trainer.shape.num_features
        rng = np.random.default_rng(seed)
        graph = TrafficGraph(rng.random((n, f), dtype=np.float32), np.ones((n, n), np.uint8),
                             np.ones(n, bool), tuple(f'CAV_{i}' for i in range(n)))
        network = trainer.agent.online.eval()
        samples = []
        for _ in range(1000):
            started = time.perf_counter()
            q_values(network, graph, np.full(6, 0.25))
            samples.append((time.perf_counter() - started) * 1000)
        samples = np.array(samples[50:])
        lines.append(f'  greedy inference, {n} vehicles all CAVs, one forward: median {np.median(samples):.3f} ms, '
                     f'p99 {np.percentile(samples, 99):.3f} ms')
        trainer.env.close()
    with_learning, without = timings['with learning'][0], timings['without learning'][0]
    lines.append(f'  learning slows the environment by {without / with_learning:.1f}x')
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
