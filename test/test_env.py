"""The gymnasium environment over simulation + graph + reward."""
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from exit_decision.env import ExitDecisionEnv


@pytest.fixture()
def env(project_config):
    environment = ExitDecisionEnv(project_config, mode='AGGI')
    yield environment
    environment.close()


def test_gymnasium_api_conformance(env):
    check_env(env, skip_render_check=True)


def test_a_decision_holds_for_the_interval_and_sums_the_reward(env, project_config):
    observation, info = env.reset(seed=3)
    keep = env.actions.index(0, 0.0)
    while not env.graph.cav_mask.any():
        observation, _, _, _, info = env.step(np.full(env.graph.num_nodes, keep))
    assert observation['features'].shape == (60, env.graph_builder.num_features)
    row = int(env.graph.cav_rows()[0])
    vehicle_id = env.graph.vehicle_ids[row]
    speed = env.sim.snapshot.by_id[vehicle_id].speed
    action = np.full(env.graph.num_nodes, keep)
    action[row] = env.actions.index(0, -2.0)
    return_before = env.episode_log.metrics()['reward']
    _, reward, _, _, info = env.step(action)
    steps = info['step_results']
    assert len(steps) == project_config.env.decision_interval
    after = {v.vehicle_id: v for v in steps[-1].vehicles}[vehicle_id]
    assert after.speed == pytest.approx(max(0.0, speed - 2.0 * 0.1 * len(steps)))
    assert reward == pytest.approx(env.episode_log.metrics()['reward'] - return_before)
    assert env.graph.vehicle_ids[row] == vehicle_id, 'a vehicle keeps its row'


def test_an_episode_ends_and_its_metrics_are_complete(project_config):
    env = ExitDecisionEnv(project_config, cav_driver='sumo')
    try:
        env.reset(seed=0)
        idle = np.zeros(env.graph.num_nodes, dtype=np.int64)
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, _ = env.step(idle)
        metrics = env.episode_log.metrics()
    finally:
        env.close()
    assert terminated and not truncated
    assert metrics['p_collision_CAV'] == 0.0 and metrics['p_CAV'] >= 0.9
    assert 10.0 < metrics['v_AVs'] < 25.0
