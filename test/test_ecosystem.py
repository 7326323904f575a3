"""The environment in the ecosystem's shapes: gymnasium.make and the PettingZoo ParallelEnv."""
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import exit_decision
from exit_decision.config import load_project

#: a scenario override (merged over scenario.yaml) for short episodes: 9 vehicles, 3 of them CAVs
SMALL = {'max_steps': 300, 'vehicle_classes': {'HV1': {'count': 3}, 'HV2': {'count': 2}, 'HV3': {'count': 1},
                                                'CAV': {'count': 3}}}


def test_import_registers_the_env_without_loading_the_simulation_rclpy_or_torch():
    code = ('import sys, gymnasium, exit_decision; '
            'assert exit_decision.ENV_ID in gymnasium.registry; '
            'print(sorted(m for m in ("torch", "rclpy", "libsumo", "pettingzoo", "exit_decision.env") if m in sys.modules))')
    result = subprocess.run([sys.executable, '-c', code], cwd=Path(__file__).resolve().parent.parent,
                            capture_output=True, text=True, check=True)
    assert result.stdout.strip() == '[]'


def test_gymnasium_make_builds_the_shipped_config_and_takes_mode_and_scenario():
    shipped = load_project()
    env = gymnasium.make(exit_decision.ENV_ID)
    assert env.unwrapped.mode == shipped.env.mode
    assert env.unwrapped.config == shipped
    assert env.observation_space['features'].shape[0] == shipped.graph.max_vehicles
    env.close()
    env = gymnasium.make(exit_decision.ENV_ID, mode='AGGI', scenario=SMALL)
    try:
        assert env.unwrapped.mode == 'AGGI'
        assert env.unwrapped.config.scenario.vehicle_classes['CAV'].count == 3
        check_env(env.unwrapped, skip_render_check=True)
    finally:
        env.close()


@pytest.fixture()
def parallel():
    env = exit_decision.parallel_env(mode='CONP', scenario=SMALL)
    yield env
    env.close()


def test_parallel_env_passes_the_pettingzoo_api_test(parallel):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        parallel_api_test(parallel, num_cycles=300)
    # PettingZoo only warns when a live agent misses a key or a finished one is given one
    assert not [str(w.message) for w in caught if 'turn' in str(w.message) or 'Live agent' in str(w.message)]


def test_agents_come_and_go_with_the_cavs_and_share_the_decision_reward(parallel):
    env = parallel.env
    assert parallel.possible_agents == ['CAV_0', 'CAV_1', 'CAV_2']
    observations, infos = parallel.reset(seed=0)
    assert parallel.agents and set(observations) == set(parallel.agents)
    keep = env.actions.index(0, 0.0)
    seen, finished, credited = set(parallel.agents), set(), 0
    while parallel.agents:
        for agent in parallel.agents:
            row = env.graph.row_of()[agent]
            assert np.array_equal(observations[agent][0, :-2], env.graph.features[row]), 'row 0 is the agent itself'
            assert observations[agent][:, -1].sum() == env.graph.adjacency[row].sum(), 'then its graph neighbours'
        # everyone keeps lane and speed where the shield allows it, else its nearest allowed action
        actions = {a: int(min(np.flatnonzero(infos[a]['action_mask']), key=lambda i: abs(i - keep)))
                   for a in parallel.agents}
        log_before, step_before = env.episode_log.metrics()['reward'], env.sim.state.step
        observations, rewards, terminations, truncations, infos = parallel.step(actions)
        assert set(actions) <= set(rewards)
        if env.sim.state.step - step_before <= env.config.env.decision_interval:   # no empty decision held through
            assert sum(rewards.values()) == pytest.approx(env.episode_log.metrics()['reward'] - log_before)
            credited += 1
        finished |= {a for a in rewards if terminations[a] or truncations[a]}
        seen |= set(parallel.agents)
    assert credited > 10
    assert seen == finished == set(parallel.possible_agents)
    with pytest.raises(ValueError, match='CAV_0: not live agents'):
        parallel.step({'CAV_0': keep})


def test_following_the_action_mask_keeps_cavs_out_of_collisions(parallel):
    def cav_collisions(masked: bool) -> float:
        rng = np.random.default_rng(0)
        total = 0.0
        for seed in range(3):
            _, infos = parallel.reset(seed=seed)
            while parallel.agents:
                size = parallel.action_space(parallel.agents[0]).n
                _, _, _, _, infos = parallel.step({
                    a: int(rng.choice(np.flatnonzero(infos[a]['action_mask']) if masked else size))
                    for a in parallel.agents})
            total += parallel.env.episode_log.metrics()['p_collision_CAV']
        return total
    assert cav_collisions(masked=False) > 0, 'random actions must be dangerous here for the test to mean anything'
    assert cav_collisions(masked=True) == 0
