"""Every learned method of config/training.yaml on the one agent loop: the encoders on
hand-made traffic, prioritized replay against hand-computed values, and a smoke run per
method that ends in an evaluable checkpoint."""
import math

import numpy as np
import pytest

from conftest import make_vehicle
from exit_decision.config import load_project
from exit_decision.encoders import GRID_CELLS, StateEncoder
from exit_decision.graph import GraphBuilder
from exit_decision.learning.replay import PrioritizedSampler
from exit_decision.learning.trainer import Trainer
from exit_decision.driving.policy import PolicyDriver
from exit_decision.model.modes import ModeWeights
from exit_decision.model.policy import PolicyController, load_policy
from exit_decision.traffic import INTENTION_LEFT, TrafficSnapshot
from test_training import TINY, rows

from ros_helpers import small_config_dir

LIMIT = 25.0


def encoded(name, vehicles):
    config = load_project()
    builder = GraphBuilder(config.graph, 450.0, LIMIT, 3)
    graph = builder.build(vehicles)
    encoder = StateEncoder(name, builder.num_features, 3, LIMIT)
    return encoder, encoder.encode(graph, TrafficSnapshot(vehicles)), graph.row_of()


def test_grid_encoder_marks_the_ego_and_the_occupied_cells():
    ego = make_vehicle('CAV.0', 'CAV', lane=1, position=100.0, speed=20.0)
    ahead_left = make_vehicle('HV1.0', lane=2, position=112.0, speed=15.0)   # 2.4 cells ahead -> cell 7
    behind_right = make_vehicle('HV1.1', lane=0, position=80.0, speed=10.0)  # 4 cells behind -> cell 1
    far = make_vehicle('HV1.2', lane=1, position=200.0)                      # outside the 10 cells
    encoder, graph, row_of = encoded('grid', [ego, ahead_left, behind_right, far])
    assert encoder.num_features == 60
    cells = graph.features[row_of['CAV.0']].reshape(3, GRID_CELLS, 2)
    assert cells[1, 5].tolist() == pytest.approx([-1.0, 20.0 / LIMIT]), 'the ego in its own cell, lane 1'
    assert cells[2, 7].tolist() == pytest.approx([1.0, 15.0 / LIMIT])
    assert cells[0, 1].tolist() == pytest.approx([1.0, 10.0 / LIMIT])
    assert np.count_nonzero(cells[..., 0]) == 3, 'the far vehicle is outside the grid'
    assert not graph.features[row_of['HV1.0']].any(), 'only CAV rows are encoded'


def test_nearest_encoder_lists_the_six_nearest_nearest_first():
    ego = make_vehicle('CAV.0', 'CAV', lane=1, position=100.0, speed=20.0)
    others = [make_vehicle(f'HV1.{i}', lane=i % 3, position=100.0 + 8.0 * (i + 1), speed=22.0) for i in range(7)]
    others[0] = make_vehicle('HV1.0', lane=2, position=105.0, speed=30.0, intention=INTENTION_LEFT)
    encoder, graph, row_of = encoded('nearest', [ego, *others])
    row = graph.features[row_of['CAV.0']]
    assert encoder.num_features == 31 and row[0] == pytest.approx(20.0 / LIMIT)
    first = row[1:6]
    assert first.tolist() == pytest.approx([1.0, 5.0 / 50.0, 1 / 3, 1.0, 1.0]), \
        'exists, dx / 50 m, one lane left of 3, dv clipped to 1, changing left'
    dxs = [row[2 + 5 * i] * 50.0 for i in range(6)]
    assert dxs == pytest.approx([5.0, 16.0, 24.0, 32.0, 40.0, 48.0]), 'by distance; the 7th (56 m) left out'


def test_prioritized_sampling_probabilities_and_weights_by_hand():
    sampler = PrioritizedSampler(capacity=4, alpha=0.5, beta=0.5, epsilon=0.0)
    for index in range(3):
        sampler.added(index)
    sampler.update(np.array([0, 1, 2]), np.array([1.0, 4.0, 9.0]))   # p^alpha = 1, 2, 3
    assert sampler.probabilities() == pytest.approx([1 / 6, 2 / 6, 3 / 6])
    indices, weights = sampler.sample(200, np.random.default_rng(0))
    # w_i = (n P_i)^-beta / max_k (n P_k)^-beta with n = 3: (0.5)^-0.5, 1^-0.5, (1.5)^-0.5 over (0.5)^-0.5
    expected = {0: 1.0, 1: math.sqrt(0.5), 2: math.sqrt(0.5 / 1.5)}
    assert {int(i): float(w) for i, w in zip(indices, weights)} == pytest.approx(expected)
    assert np.bincount(indices, minlength=3)[2] > np.bincount(indices, minlength=3)[0], 'drawn by priority'
    sampler.added(3)
    assert sampler.priorities[3] == pytest.approx(3.0), 'a new transition gets the largest priority seen (9^0.5)'


@pytest.fixture(scope='module')
def config_dir(tmp_path_factory):
    return small_config_dir(tmp_path_factory.mktemp('cfg') / 'config')


@pytest.mark.parametrize('method', load_project().training.method_names)   # the published rows too
def test_each_method_trains_and_leaves_an_evaluable_checkpoint(method, config_dir, tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    trainer = Trainer(config, method, 'CONP', 0, tmp_path / 'run')
    policy = load_policy(trainer.run(episodes=1, progress=False))
    log = rows(tmp_path / 'run' / 'training.csv')
    assert all(math.isfinite(float(row['loss'])) for row in log)
    assert policy.metadata['algorithm'] == method and policy.encoder.name == config.training.method(method).encoder
    env = trainer.env.__class__(config, mode='CONP')
    driver = PolicyDriver(PolicyController(policy, env.shield, planner=env.planner), None,
                          ModeWeights(config).mode('CONP'))   # what evaluation and the node run
    decided = 0
    try:
        env.reset(seed=10_000)
        for _ in range(30):
            q = policy.q_values(env.graph, env.sim.snapshot)
            assert q.shape == (config.graph.max_vehicles, trainer.env.actions.size) and np.isfinite(q).all()
            decision = driver.decide(env.graph, env.sim.snapshot, env.sim.state.time)
            decided += len(decision.actions)
            env.step(np.full(env.graph.num_nodes, env.actions.index(0, 0.0)))
    finally:
        env.close()
    assert decided > 0, 'the checkpoint decided for CAVs'


def test_sgrl_training_env_lets_the_policy_drive_one_cav_at_a_time(config_dir):
    from exit_decision.env import ExitDecisionEnv

    env = ExitDecisionEnv(load_project(config_dir), single_agent=True)
    most_cavs, most_controlled = 0, 0
    try:
        env.reset(seed=3)
        keep = env.actions.index(0, 0.0)
        done = False
        while not done:
            vehicles = env.sim.snapshot.vehicles
            most_cavs = max(most_cavs, sum(v.is_cav for v in vehicles))
            most_controlled = max(most_controlled, sum(v.controlled for v in vehicles))
            _, _, terminated, truncated, _ = env.step(np.full(env.graph.num_nodes, keep))
            done = terminated or truncated
    finally:
        env.close()
    assert most_cavs > 1 and most_controlled == 1, 'other CAVs are in the human block while one learns'


@pytest.mark.parametrize('method, reward, kind', [('dqn_published', 'paper_002', 'terms'),
                                                  ('sgrl_published', 'paper_001', 'intention')])
def test_a_baseline_as_published_learns_its_papers_reward_without_our_measures(method, reward, kind, config_dir,
                                                                               tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    trainer = Trainer(config, method, 'CONP', 0, tmp_path / 'run')
    policy = load_policy(trainer.run(episodes=1, progress=False))
    assert len(trainer.experience.demos) == 0 and trainer.state.updates > 0, 'it learnt from its own experience alone'
    assert trainer.env.learning_reward_fn.config.kind == kind, 'it learnt from its paper\'s reward'
    assert trainer.env.reward_fn.config.kind == 'matrix', 'its returns are scored under the mode, as every method\'s'
    assert (policy.metadata['measures'], policy.metadata['reward_variant']) == (False, reward)
    env = trainer.env.__class__(config, mode='CONP')
    try:
        controller = PolicyController(policy, env.shield, planner=env.planner)   # what evaluation and the node run
        layers = controller.shield.config
        assert not (layers.lane_gap or layers.stop_capable or layers.human_follower_braking or layers.gap_reservation)
        assert controller.planner is None and env.planner is not None
        env.reset(seed=10_000)
        while not env.graph.cav_mask.any():
            env.step(np.full(env.graph.num_nodes, env.actions.index(0, 0.0)))
        driver = PolicyDriver(controller, None, ModeWeights(config).mode('CONP'))
        assert driver.decide(env.graph, env.sim.snapshot, env.sim.state.time).actions, 'the checkpoint decides'
    finally:
        env.close()
