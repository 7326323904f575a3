"""Playing training episodes and turning them into m-step transitions (docs/design.md, "Learning").

Per decision: the Q values of the graph (one forward for all rows), then each CAV chooses
under the shield, front to back: epsilon-greedy, the random action biased towards keeping
the lane and a small acceleration; the env holds the actions for the decision interval; the
m-step accumulator emits transitions whose returns are reward *vectors*
(``exit_decision.reward``), scored under mode weights only when sampled. Over options, the
rows whose option ended choose and the low level makes the commands. Without a network the
demonstrator drives (the demonstrations DQfD learns from).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from exit_decision.actions import NO_ACTION
from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ExplorationConfig
from exit_decision.encoders import StateEncoder
from exit_decision.env import ExitDecisionEnv
from exit_decision.learning.replay import DecisionRecord, EpisodeAccumulator, Transition
from exit_decision.model.networks import GraphQNetwork
from exit_decision.model.policy import greedy_decision, q_values

#: called after every decision with the transitions it emitted (learning as the episode goes)
OnDecision = Callable[[list[Transition]], None]


class Collector:
    """Plays episodes in ``env``, on the grid or over its options. ``shield`` and ``planner``:
    what the learned policy chooses under (a method as published: the bare shield, no
    planner); ``rng``: the run's generator (exploration)."""

    def __init__(self, env: ExitDecisionEnv, encoder: StateEncoder, demonstrator: RuleBasedDriver, shield,
                 planner, exploration: ExplorationConfig, multi_step: int, gamma: float, rng: np.random.Generator):
        self.env, self.encoder, self.demonstrator = env, encoder, demonstrator
        self.shield, self.planner, self.exploration = shield, planner, exploration
        self.multi_step, self.gamma, self.rng = multi_step, gamma, rng
        self.grid, self.options = env.actions, env.options   # options: None on the grid

    def episode(self, seed: int, network: GraphQNetwork | None = None, weights: np.ndarray | None = None,
                epsilon: float = 0.0, on_decision: OnDecision | None = None) -> list[Transition]:
        """One episode, by the demonstrator (``network`` None) or epsilon-greedy on ``network``'s
        Q values (``weights``: a conditioned network's mode weights); returns its transitions."""
        play = self._grid_episode if self.options is None else self._option_episode
        return play(seed, network, weights, epsilon, on_decision)

    def _grid_episode(self, seed, network, weights, epsilon, on_decision) -> list[Transition]:
        env = self.env
        env.reset(seed=seed)
        accumulator = EpisodeAccumulator(self.multi_step, self.gamma)
        transitions = []
        keep = self.grid.index(0, 0.0)
        while True:
            graph, snapshot = env.graph, env.sim.snapshot
            observed = self.encoder.encode(graph, snapshot)
            if network is None:
                decision = self.demonstrator.decide(graph, snapshot)
            else:
                q = q_values(network, observed, weights)
                decision = greedy_decision(self.shield, graph, snapshot, q, explore=lambda mask: (
                    self.explore(mask) if self.rng.random() < epsilon else None), planner=self.planner)
            actions, masks = self.decision_arrays(graph, decision)
            _, _, terminated, truncated, info = env.step(np.where(actions >= 0, actions, keep))
            own, shared = info['reward_vector']
            emitted = accumulator.add(DecisionRecord(observed, actions, masks, own, shared))
            if terminated or truncated:
                emitted += accumulator.finish(self.final_record(), terminated)
            transitions += emitted
            if on_decision is not None:
                on_decision(emitted)
            if terminated or truncated:
                return transitions

    def _option_episode(self, seed, network, weights, epsilon, on_decision) -> list[Transition]:
        """Over options: the rows whose option ended choose (the demonstrator: the neutral style
        on the route's lane plan, the same for every mode; the policy: epsilon-greedy over the
        allowed options), every CAV row acts with the option it holds."""
        env, space = self.env, self.options
        _, info = env.reset(seed=seed)
        accumulator = EpisodeAccumulator(self.multi_step, self.gamma)
        transitions = []
        neutral = space.index('route', 'neutral')
        while True:
            graph = env.graph
            observed = self.encoder.encode(graph, env.sim.snapshot)
            choosing, masks, held = info['choosing'], info['option_masks'], info['options']
            if network is None:
                chosen = np.full(graph.num_nodes, neutral)
            else:
                q = np.where(masks, q_values(network, observed, weights), -np.inf)
                chosen = q.argmax(1)
                for row in np.flatnonzero(choosing):
                    if self.rng.random() < epsilon:
                        chosen[row] = self.rng.choice(np.flatnonzero(masks[row]))
            actions = np.where(choosing, chosen, held).astype(np.int64)
            actions[~graph.cav_mask.astype(bool)] = NO_ACTION
            _, _, terminated, truncated, info = env.step(np.where(actions >= 0, actions, neutral))
            own, shared = info['reward_vector']
            emitted = accumulator.add(DecisionRecord(observed, actions, masks, own, shared, choosing))
            if terminated or truncated:
                emitted += accumulator.finish(self.final_record(info), terminated)
            transitions += emitted
            if on_decision is not None:
                on_decision(emitted)
            if terminated or truncated:
                return transitions

    def explore(self, mask: np.ndarray) -> int:
        """A random allowed action; biased: usually keep the lane, acceleration ~ N(0, std),
        the nearest allowed (a uniform random action changes lane 2 times in 3 and brakes)."""
        e, grid = self.exploration, self.grid
        if not e.biased:
            return int(self.rng.choice(np.flatnonzero(mask)))
        changes = [c for c in grid.lane_changes if (mask & grid.rows(c)).any()]
        if 0 in changes and (len(changes) == 1 or self.rng.random() < e.keep_lane_probability):
            change = 0
        else:
            sides = [c for c in changes if c != 0] or changes
            change = sides[self.rng.integers(len(sides))]
        candidates = np.flatnonzero(mask & grid.rows(change))
        wanted = self.rng.normal(0.0, e.acceleration_std)
        return int(candidates[np.argmin(np.abs(grid.acceleration_of[candidates] - wanted))])

    def decision_arrays(self, graph, decision) -> tuple[np.ndarray, np.ndarray]:
        """A decision's actions and action masks as (N,) and (N, A) arrays by graph row."""
        n = graph.num_nodes
        actions = np.full(n, NO_ACTION, np.int64)
        masks = np.zeros((n, self.grid.size), bool)
        row_of = graph.row_of()
        for vehicle_id, action in decision.actions.items():
            actions[row_of[vehicle_id]] = action
            masks[row_of[vehicle_id]] = decision.masks[vehicle_id]
        return actions, masks

    def final_record(self, info: dict | None = None) -> DecisionRecord:
        """The last state, with the masks its CAVs would choose under (for bootstrapping; over
        options, the step's ``info`` has them, and every row chooses anew there)."""
        graph, planner = self.env.graph, self.planner
        if self.options is not None:
            return DecisionRecord(self.encoder.encode(graph, self.env.sim.snapshot),
                                  np.full(graph.num_nodes, NO_ACTION, np.int64), info['option_masks'],
                                  choosing=np.ones(graph.num_nodes, bool))
        snapshot = self.env.sim.snapshot
        masks = np.zeros((graph.num_nodes, self.grid.size), bool)
        for vehicle_id, row in graph.row_of().items():
            if graph.cav_mask[row]:
                vehicle = snapshot.by_id[vehicle_id]
                mask = self.shield.mask(vehicle, snapshot)
                masks[row] = planner.restrict(vehicle, mask) if planner is not None else mask
        return DecisionRecord(self.encoder.encode(graph, snapshot), np.full(graph.num_nodes, NO_ACTION, np.int64),
                              masks)
