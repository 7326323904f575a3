"""Gymnasium environment: the scenario as a multi-agent decision problem on a graph.

One ``step`` is one decision: every CAV row of the action vector gets its own action from
the ``ActionGrid``, which is held for ``decision_interval`` simulation steps (a lane change
is issued once). The reward is the shared scalar of the reward function matrix, summed over
the interval. Observations are the graph of ``exit_decision.graph`` as a dict of arrays;
``env.graph`` is the full ``TrafficGraph`` of the last observation (with vehicle ids).
"""
from __future__ import annotations

from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig
from exit_decision.evaluation.metrics import EpisodeLog
from exit_decision.graph import GraphBuilder, TrafficGraph
from exit_decision.reward import StepRewardInputs, make_reward
from exit_decision.scenario.simulation import Backend, CavDriver, HighwaySimulation
from exit_decision.traffic import StepResult

LANE_CHANGE_WINDOW = 0.5   # [s] the reward's m counts lane changes over this window


class ExitDecisionEnv(gym.Env):
    metadata = {'render_modes': []}

    def __init__(self, config: ProjectConfig, mode: str | None = None, reward_variant: str | None = None,
                 cav_driver: CavDriver = 'policy', backend: Backend = 'libsumo'):
        self.config = config
        self.mode = mode or config.env.mode
        scenario = config.scenario
        self.sim = HighwaySimulation(scenario, cav_driver=cav_driver, backend=backend)
        self.graph_builder = GraphBuilder(config.graph, self.sim.geometry.road_length,
                                          scenario.road.highway_speed_limit, scenario.road.lane_count)
        self.actions = ActionGrid(config.env.actions)
        self.shield = Shield.of(config, self.actions, self.sim.geometry)
        self.reward_fn = make_reward(config.reward(reward_variant or config.env.reward_variant),
                                     config.mode(self.mode), scenario.emergency_braking_threshold)
        n, f = config.graph.max_vehicles, self.graph_builder.num_features
        self.observation_space = spaces.Dict({
            'features': spaces.Box(-1.0, np.inf, (n, f), np.float32),
            'adjacency': spaces.MultiBinary((n, n)),
            'cav_mask': spaces.MultiBinary(n),
        })
        self.action_space = spaces.MultiDiscrete(np.full(n, self.actions.size))
        self._window = max(1, round(LANE_CHANGE_WINDOW / scenario.step_length))
        self.graph: TrafficGraph | None = None

    def _observation(self) -> dict[str, np.ndarray]:
        g = self.graph
        return {'features': g.features, 'adjacency': g.adjacency, 'cav_mask': g.cav_mask.astype(np.int8)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        episode_seed = seed if seed is not None else int(self.np_random.integers(2**31 - 1))
        result = self.sim.reset(episode_seed)
        self.graph_builder.reset()
        self.graph = self.graph_builder.build(result.vehicles, self.sim.snapshot)
        self.episode_log = EpisodeLog(self.config.scenario.emergency_braking_threshold)
        self._lane_changes = deque(maxlen=self._window)
        return self._observation(), {'seed': episode_seed}

    def cav_ids(self) -> list[str]:
        """Vehicle ids of the CAV rows of the current graph, in row order."""
        return [self.graph.vehicle_ids[row] for row in self.graph.cav_rows()]

    def commands(self, action: np.ndarray) -> dict:
        """The commands of an action vector (one entry per graph row; CAV rows are used)."""
        action = np.asarray(action)
        if action.shape != (self.graph.num_nodes,):
            raise ValueError(f'action must have shape ({self.graph.num_nodes},), got {action.shape}')
        if self.sim.cav_driver != 'policy':
            return {}
        return {self.graph.vehicle_ids[row]: self.actions.command(int(action[row]))
                for row in self.graph.cav_rows()}

    def simulate_step(self, commands: dict | None = None) -> tuple[StepResult, float]:
        """One simulation step (new commands, or None to hold), its reward, logged in the
        episode log. ``step`` is made of these; the ROS bridge calls it directly."""
        result = self.sim.step(commands)
        self._lane_changes.append(len(result.lane_changers))
        reward = self.reward_fn(StepRewardInputs(result, self.sim.snapshot, sum(self._lane_changes))).total
        self.episode_log.record(result, reward)
        return result, reward

    def step(self, action):
        commands = self.commands(action)
        total = 0.0
        results = []
        for k in range(self.config.env.decision_interval):
            result, reward = self.simulate_step(commands if k == 0 else None)
            total += reward
            results.append(result)
            if result.terminated or result.truncated:
                break
        self.graph = self.graph_builder.build(result.vehicles, self.sim.snapshot)
        info = {'step_results': results}
        return self._observation(), total, result.terminated, result.truncated and not result.terminated, info

    def close(self) -> None:
        self.sim.close()
