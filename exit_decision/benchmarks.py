"""Benchmark commands: figures printed, never asserted in tests."""
from __future__ import annotations

import time

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
