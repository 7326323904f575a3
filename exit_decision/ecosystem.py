"""The environment in the ecosystem's own shapes: a gymnasium id and a PettingZoo ParallelEnv.

``gymnasium.make('exit_decision/HighwayExit-v0')`` (registered on ``import exit_decision``)
builds ``ExitDecisionEnv`` through ``make_env``; ``parallel_env`` wraps the same env as one
PettingZoo agent per CAV, so RLlib, TorchRL or any PettingZoo user trains without our trainer:

- agents: the ids of the CAVs the policy drives now (``CAV_<serial>``); possible_agents:
  every CAV id the scenario can spawn. A CAV that leaves the road (exit, collision) or is
  handed to SUMO's driver after a missed exit terminates. Decisions with no CAV on the road
  are stepped through with every vehicle holding (no one acts, so no one is credited), so a
  live episode always has an agent.
- action: an index of the action grid (``exit_decision.actions``, 81 by default); an agent
  given no action keeps its lane and speed.
- reward: the trainer's per-CAV credit (``reward.credit``: the CAV's own part of
  ``info['reward_vector']`` plus an equal share of the shared part) scored with
  ``reward.scalar`` under the env's mode.
- observation (N, F + 2) float32, a fixed-size ego view of the graph: row 0 is the agent's
  own feature row, the next rows are its graph neighbours (every CAV, the humans within
  sensing range: what the GCN aggregates over), nearest first; columns are the graph's F
  features, then ``is_cav`` and ``present`` (1 on filled rows); the rest is zeros. A
  finished agent's last observation is all zeros when its vehicle is gone.
- ``infos[agent]['action_mask']``: (A,) bool, the shield's mask for that CAV (narrowed to its
  route lanes when the config's lane planner is on), the mask our policies choose under.
  Masks are per CAV: the gap reservation between CAVs deciding together is not in them, and
  the lane planner does not take over CAVs off their route here (the agent drives them).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from exit_decision.actions import NO_ACTION
from exit_decision.config import load_project
from exit_decision.env import ExitDecisionEnv
from exit_decision.reward import credit, scalar
from exit_decision.traffic import CAV, vehicle_id_of

#: the extra columns of a PettingZoo observation, after the graph's features
EGO_COLUMNS = ('is_cav', 'present')


def make_env(mode: str | None = None, config_dir: Path | str | None = None,
             scenario: Path | str | dict | None = None) -> ExitDecisionEnv:
    """The env of a config directory (default: the shipped one), under ``mode`` (default:
    env.yaml's), with ``scenario`` (a YAML file or a dict) merged over scenario.yaml."""
    return ExitDecisionEnv(load_project(config_dir, scenario), mode=mode)


def parallel_env(mode: str | None = None, config_dir: Path | str | None = None,
                 scenario: Path | str | dict | None = None) -> HighwayExitParallelEnv:
    """One PettingZoo agent per CAV over ``make_env``'s environment (same arguments)."""
    return HighwayExitParallelEnv(make_env(mode, config_dir, scenario))


class HighwayExitParallelEnv(ParallelEnv):
    metadata: ClassVar[dict[str, Any]] = {'name': 'exit_decision_highway_exit_v0', 'render_modes': []}

    def __init__(self, env: ExitDecisionEnv):
        self.env = env
        config = env.config
        self.possible_agents = [vehicle_id_of(CAV, serial)
                                for serial in range(config.scenario.vehicle_classes[CAV].count)]
        self.agents: list[str] = []
        n, f = config.graph.max_vehicles, env.graph_builder.num_features
        self._position = env.graph_builder.feature_names.index('position')
        self._keep = env.actions.index(0, 0.0)
        self._shape = (n, f + len(EGO_COLUMNS))
        # one space object per agent for the env's life (PettingZoo's rule; seeding an action
        # space seeds that agent's samples)
        self.observation_spaces = dict.fromkeys(self.possible_agents, spaces.Box(-1.0, np.inf, self._shape, np.float32))
        self.action_spaces = {agent: spaces.Discrete(env.actions.size) for agent in self.possible_agents}
        self._masks: dict[str, np.ndarray] = {}

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    # --- views of the graph -------------------------------------------------------------------

    def _observe(self, row: int | None) -> np.ndarray:
        """The ego view of the vehicle in ``row`` (module docstring); zeros for None."""
        obs = np.zeros(self._shape, np.float32)
        if row is None:
            return obs
        graph = self.env.graph
        others = np.flatnonzero(graph.adjacency[row])
        others = others[others != row]
        distance = np.abs(graph.features[others, self._position] - graph.features[row, self._position])
        rows = np.concatenate([[row], others[np.argsort(distance, kind='stable')]])
        f = graph.features.shape[1]
        obs[:len(rows), :f] = graph.features[rows]
        obs[:len(rows), f] = graph.cav_mask[rows]
        obs[:len(rows), f + 1] = 1.0
        return obs

    def _update_masks(self) -> None:
        shield, planner, snapshot = self.env.shield, self.env.planner, self.env.sim.snapshot
        self._masks = {}
        for agent in self.agents:
            vehicle = snapshot.by_id[agent]
            mask = shield.mask(vehicle, snapshot)
            self._masks[agent] = planner.restrict(vehicle, mask) if planner is not None else mask

    def _hold_until_a_cav(self) -> tuple[bool, bool]:
        """Step with every vehicle holding while no CAV is on the road and the episode goes on;
        returns (terminated, truncated) of the last step."""
        terminated = truncated = False
        while not (terminated or truncated) and not self.env.graph.cav_mask.any():
            _, _, terminated, truncated, _ = self.env.step(np.full(self.env.graph.num_nodes, self._keep))
        return terminated, truncated

    def _live(self, terminated: bool, truncated: bool) -> None:
        self.agents = [] if terminated or truncated else self.env.graph.cav_ids()
        self._update_masks()

    # --- the PettingZoo API ------------------------------------------------------------------

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        self.env.reset(seed=seed, options=options)
        self._live(*self._hold_until_a_cav())
        row_of = self.env.graph.row_of()
        return ({agent: self._observe(row_of[agent]) for agent in self.agents},
                {agent: {'action_mask': self._masks[agent]} for agent in self.agents})

    def step(self, actions: dict[str, int]):
        env, graph = self.env, self.env.graph
        unknown = sorted(set(actions) - set(self.agents))
        if unknown:
            raise ValueError(f'actions for {", ".join(unknown)}: not live agents (live: {", ".join(self.agents)})')
        row_of = graph.row_of()
        acting = list(self.agents)
        chosen = np.full(graph.num_nodes, NO_ACTION, np.int64)
        for agent in acting:
            chosen[row_of[agent]] = int(actions.get(agent, self._keep))
        _, _, terminated, truncated, info = env.step(np.where(chosen >= 0, chosen, self._keep))
        own, shared = info['reward_vector']
        scores = scalar(credit(own, shared, chosen >= 0), env.mode_weights)
        if not (terminated or truncated):
            terminated, truncated = self._hold_until_a_cav()
        self._live(terminated, truncated)
        now = env.graph.row_of()
        present = set(env.graph.cav_ids())   # a CAV handed to SUMO's driver is no longer one
        reported = acting + [agent for agent in self.agents if agent not in acting]   # those that acted, and newcomers
        observations = {agent: self._observe(now[agent] if agent in present else None)
                        for agent in reported}
        rewards = {agent: float(scores[row_of[agent]]) if agent in acting else 0.0 for agent in reported}
        terminations = {agent: agent not in present or terminated for agent in reported}
        truncations = {agent: agent in present and truncated and not terminated for agent in reported}
        infos = {agent: {'action_mask': self._masks[agent]} if agent in self._masks else {} for agent in reported}
        return observations, rewards, terminations, truncations, infos

    def close(self) -> None:
        self.env.close()
