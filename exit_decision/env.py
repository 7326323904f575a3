"""Gymnasium environment: the scenario as a multi-agent decision problem on a graph.

One ``step`` is one decision: every CAV row of the action vector gets its own action from
the ``ActionGrid``, which is held for ``decision_interval`` simulation steps (a lane change
is issued once); or, with ``action_space='options'``, an option (agents/options.py) that the
CAVs whose option ended begin, the rule-based low level making every CAV's command. The reward is the paper's global scalar of the reward function matrix under
the env's mode, summed over the interval (or a baseline's own reward, ``learning_reward``;
the episode log, and so every metric, stays under the matrix); ``info['reward_vector']`` holds what any mode's
scalar is made of (``exit_decision.reward``), split by owner: (N, 4, 2) for the CAV rows
that acted at this decision and (4, 2) shared (every other term, vehicles that did not act
included), so the trainer can score it under other modes and credit each CAV its own part.
Observations are the graph of ``exit_decision.graph`` as a dict of arrays; ``env.graph`` is
the full ``TrafficGraph`` of the last observation (with vehicle ids).
"""
from __future__ import annotations

from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.options import OptionExecutor, OptionSpace
from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.agents.shield import Shield
from exit_decision.config import ActionSpaceName, ProjectConfig, RuleBasedConfig
from exit_decision.episode_log import EpisodeLog
from exit_decision.graph import GraphBuilder, TrafficGraph
from exit_decision.reward import RewardVector, StepRewardInputs, make_reward, scalar
from exit_decision.scenario.simulation import Backend, CavDriver, HighwaySimulation
from exit_decision.traffic import StepResult

LANE_CHANGE_WINDOW = 0.5   # [s] the reward's m counts lane changes over this window


class ExitDecisionEnv(gym.Env):
    metadata = {'render_modes': []}

    def __init__(self, config: ProjectConfig, mode: str | None = None, reward_variant: str | None = None,
                 cav_driver: CavDriver = 'policy', backend: Backend = 'libsumo', keep_step_inputs: bool = False,
                 single_agent: bool = False, learning_reward: str | None = None,
                 action_space: ActionSpaceName = 'grid'):
        self.config = config
        # the episode's reward inputs, kept to score it under other reward variants afterwards
        self.step_inputs: list[StepRewardInputs] | None = [] if keep_step_inputs else None
        self.mode = mode or config.env.mode
        scenario = config.scenario
        self.sim = HighwaySimulation(scenario, cav_driver=cav_driver, backend=backend, single_agent=single_agent)
        self.graph_builder = GraphBuilder(config.graph, self.sim.geometry.road_length,
                                          scenario.road.highway_speed_limit, scenario.road.lane_count)
        self.actions = ActionGrid(config.env.actions)
        self.shield = Shield.of(config, self.actions, self.sim.geometry)
        self.planner = LanePlanner.of(config, self.shield)   # for learned policies; None: off
        # reward_fn scores the episode log (every metric); the agent learns from learning_reward_fn
        # (``learning_reward``: a baseline's own reward, e.g. a paper's; default: the same)
        def reward_of(variant: str):
            return make_reward(config.reward(variant), scenario.step_length, scenario.emergency_braking_threshold,
                               self.sim.geometry.route_lanes)
        #: the reward variant every metric and the episode's reward vector are scored under
        self.reward_variant = scored = reward_variant or config.env.reward_variant
        self.reward_fn = reward_of(scored)
        self.learning_reward_fn = self.reward_fn if learning_reward in (None, scored) else reward_of(learning_reward)
        self.mode_weights = self.reward_fn.weights(config.mode(self.mode))
        self.learning_weights = self.learning_reward_fn.weights(config.mode(self.mode))
        n, f = config.graph.max_vehicles, self.graph_builder.num_features
        self.observation_space = spaces.Dict({
            'features': spaces.Box(-1.0, np.inf, (n, f), np.float32),
            'adjacency': spaces.MultiBinary((n, n)),
            'cav_mask': spaces.MultiBinary(n),
        })
        #: ``options``: each CAV row's action is an option (agents/options.py), read only for the
        #: rows whose option ended (``info['choosing']``); the executor makes the commands
        self.options = OptionSpace(config, self.shield, self.planner) if action_space == 'options' else None
        self.executor = OptionExecutor(self.options) if self.options is not None else None
        size = self.options.size if self.options is not None else self.actions.size
        self.action_space = spaces.MultiDiscrete(np.full(n, size))
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
        self.episode_log = EpisodeLog(self.config.scenario.emergency_braking_threshold, reward_weights=self.mode_weights)
        self._lane_changes = deque(maxlen=self._window)
        if self.step_inputs is not None:
            self.step_inputs.clear()
        if self.executor is not None:
            self.executor.reset()
        return self._observation(), {'seed': episode_seed, **self._option_info()}

    def _option_info(self) -> dict[str, np.ndarray]:
        """With options, what the next decision needs: ``choosing`` (N,) the CAV rows whose
        option ended (only their actions are read), ``option_masks`` (N, options) the options
        each may begin, and ``options`` (N,) the option each row holds (-1: none)."""
        if self.executor is None:
            return {}
        graph, snapshot, time = self.graph, self.sim.snapshot, self.sim.state.time
        choosing = np.zeros(graph.num_nodes, dtype=bool)
        masks = np.zeros((graph.num_nodes, self.options.size), dtype=bool)
        held = np.full(graph.num_nodes, -1)
        for row in graph.cav_rows():
            vehicle = snapshot.by_id[graph.vehicle_ids[row]]
            choosing[row] = self.executor.ended(vehicle, time)
            masks[row] = self.options.mask(vehicle)
            if vehicle.vehicle_id in self.executor.held:
                held[row] = self.executor.held[vehicle.vehicle_id].index
        return {'choosing': choosing, 'option_masks': masks, 'options': held}

    def commands(self, action: np.ndarray) -> dict:
        """The commands of an action vector (one entry per graph row; CAV rows are used)."""
        action = np.asarray(action)
        if action.shape != (self.graph.num_nodes,):
            raise ValueError(f'action must have shape ({self.graph.num_nodes},), got {action.shape}')
        if self.sim.cav_driver != 'policy':
            return {}
        if self.executor is not None:
            graph, snapshot = self.graph, self.sim.snapshot
            row_of, cav_ids = graph.row_of(), graph.cav_ids()
            self.executor.choose(snapshot, cav_ids, self.sim.state.time,
                                 lambda vehicle, mask: int(action[row_of[vehicle.vehicle_id]]))
            return self.executor.commands(snapshot, cav_ids)
        return {self.graph.vehicle_ids[row]: self.actions.command(int(action[row]))
                for row in self.graph.cav_rows()}

    def simulate_step(self, commands: dict | None = None) -> tuple[StepResult, RewardVector]:
        """One simulation step (new commands, or None to hold) and its learning reward vector;
        the scoring reward's is logged in the episode log. ``step`` is made of these; the ROS
        bridge calls it directly."""
        result = self.sim.step(commands)
        self._lane_changes.append(len(result.lane_changers))
        inputs = StepRewardInputs(result, self.sim.snapshot, sum(self._lane_changes))
        if self.step_inputs is not None:
            self.step_inputs.append(inputs)
        vector = self.reward_fn.vector(inputs)
        self.episode_log.record(result, vector.total(), self.sim.snapshot)
        if self.learning_reward_fn is not self.reward_fn:
            vector = self.learning_reward_fn.vector(inputs)
        return result, vector

    def rule_based_driver(self, parameters: RuleBasedConfig | None = None) -> RuleBasedDriver:
        """The rule-based driver of this environment's CAVs: the neutral driver (env.yaml's
        ``rule_based``, the same for every mode), or other ``parameters`` (the reward sanity sweep)."""
        return RuleBasedDriver(self.actions, self.shield, self.sim.geometry, self.config.scenario.road.ramp_speed_limit,
                               parameters or self.config.env.rule_based)

    def step(self, action):
        """The gymnasium step: an action vector (a grid action or an option per CAV row); with
        options, ``info`` also holds what the next decision needs (``_option_info``)."""
        observation, reward, terminated, truncated, info = self.step_commands(self.commands(action))
        return observation, reward, terminated, truncated, {**info, **self._option_info()}

    def step_commands(self, commands: dict):
        """``step`` with the CAVs' commands given directly (vehicle id -> ``CavCommand``): what
        every driver gives (``driving``), the options' low level commands that are not on the
        action grid. The one function outside the environment that steps it is
        ``driving.episode.play_episode``."""
        graph = self.graph
        acting = {vehicle_id: row for vehicle_id, row in graph.row_of().items() if graph.cav_mask[row]}
        per_row = np.zeros((graph.num_nodes, 4, 2))
        shared = np.zeros((4, 2))
        results = []
        for k in range(self.config.env.decision_interval):
            result, vector = self.simulate_step(commands if k == 0 else None)
            shared += vector.shared
            for vehicle_id, part in vector.per_vehicle.items():
                row = acting.get(vehicle_id)
                if row is None:
                    shared += part
                else:
                    per_row[row] += part
            results.append(result)
            if result.terminated or result.truncated:
                break
        self.graph = self.graph_builder.build(result.vehicles, self.sim.snapshot)
        reward = float(scalar(per_row.sum(0) + shared, self.learning_weights))
        info = {'step_results': results, 'reward_vector': (per_row, shared)}
        return self._observation(), reward, result.terminated, result.truncated and not result.terminated, info

    def close(self) -> None:
        self.sim.close()
