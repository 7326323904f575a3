"""Playing training episodes and turning them into m-step transitions (docs/design.md, "Learning").

A training episode is the one episode loop (``driving.episode``) with the driver of the network
being learnt (``driving.policy.PolicyDriver``, epsilon-greedy through ``explore``), or, without a
network, the demonstrator (the neutral rule-based driver on the grid; over options, the neutral
style on the route's lane plan, the same for every mode). The collector records each decision:
the state it was made in (encoded once, the network's Q values read the same encoding), the
actions and their masks, and the reward vectors of the interval (``exit_decision.reward``),
scored under mode weights only when sampled; the m-step accumulator emits the transitions.
Over options, only the rows whose option ended chose, and the others act with the option they hold.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from exit_decision.actions import NO_ACTION
from exit_decision.config import ActionSpaceName, ExplorationConfig, ProjectConfig
from exit_decision.driving.fixed import GridDriver, constant_option
from exit_decision.driving.interface import Driver, StepDecision
from exit_decision.driving.episode import play_episode
from exit_decision.driving.policy import PolicyDriver
from exit_decision.driving.prior import PriorDriver, PriorTable
from exit_decision.encoders import StateEncoder
from exit_decision.env import ExitDecisionEnv
from exit_decision.graph import TrafficGraph
from exit_decision.learning.replay import DecisionRecord, EpisodeAccumulator, Transition
from exit_decision.model.modes import Mode
from exit_decision.model.networks import GraphQNetwork
from exit_decision.model.policy import q_values
from exit_decision.traffic import TrafficSnapshot

#: called after every decision with the transitions it emitted (learning as the episode goes)
OnDecision = Callable[[list[Transition]], None]


class EncodedStates:
    """The encoder's view of the last graph, made once per decision (the replay keeps it and the
    network's Q values are computed from it)."""

    def __init__(self, encoder: StateEncoder):
        self.encoder = encoder
        self._last: tuple[TrafficGraph, TrafficGraph] | None = None

    def __call__(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> TrafficGraph:
        if self._last is None or self._last[0] is not graph:
            self._last = (graph, self.encoder.encode(graph, snapshot))
        return self._last[1]


class LearningQ:
    """The network being learnt as a policy driver's Q source (``driving.policy.QSource``)."""
    name = 'learning'

    def __init__(self, network: GraphQNetwork, encoded: EncodedStates, shield, planner):
        self.network, self.encoded, self.shield, self.planner = network, encoded, shield, planner

    def network_weights(self, mode: Mode) -> np.ndarray | None:
        return mode.weights if self.network.conditioned else None

    def q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot, network_weights: np.ndarray | None) -> np.ndarray:
        return q_values(self.network, self.encoded(graph, snapshot), network_weights)


def method_collector(config: ProjectConfig, algorithm: str, env_mode: str, action_space: ActionSpaceName,
                     rng: np.random.Generator, prior: PriorTable | None = None) -> Collector:
    """A training run's environment and collector for ``algorithm`` (one per process: the
    trainer's, and each Ray actor's): the method's encoder, reward and agents (SGRL trains one
    CAV at a time); as published, the bare shield and no planner (the env's serve the teacher);
    ``prior``: the prior's table, when already measured (an actor's)."""
    method, training = config.training.method(algorithm), config.training.of_method(algorithm)
    env = ExitDecisionEnv(config, mode=env_mode, single_agent=method.single_agent,
                          learning_reward=method.reward_variant, action_space=action_space)
    road = config.scenario.road
    encoder = StateEncoder(method.encoder, env.graph_builder.num_features, road.lane_count, road.highway_speed_limit)
    collector = Collector(env, encoder, env.shield if method.measures else env.shield.bare(),
                          env.planner if method.measures else None, training.exploration, method.multi_step,
                          training.gamma, rng)
    collector.prior = prior
    return collector


class Collector:
    """Plays episodes in ``env``, on the grid or over its options. ``shield`` and ``planner``:
    what the learned policy chooses under on the grid (a method as published: the bare shield,
    no planner); ``rng``: the run's generator (exploration)."""

    def __init__(self, env: ExitDecisionEnv, encoder: StateEncoder, shield, planner, exploration: ExplorationConfig,
                 multi_step: int, gamma: float, rng: np.random.Generator):
        self.env, self.encoded = env, EncodedStates(encoder)
        self.shield, self.planner, self.exploration = shield, planner, exploration
        self.multi_step, self.gamma, self.rng = multi_step, gamma, rng
        self.grid, self.options = env.actions, env.options   # options: None on the grid
        self.demonstrator: Driver = GridDriver('demonstrator', self.grid, env.rule_based_driver().decide) \
            if self.options is None else constant_option(self.options, env.config.env.options.neutral_style)
        #: the prior over options (``driving.prior``), once measured: ``exploration.around: prior``
        #: explores around its option instead of the network's greedy one
        self.prior: PriorTable | None = None

    def driver(self, network: GraphQNetwork | None, mode: Mode | None, epsilon: float) -> Driver:
        """The demonstrator (``network`` None), or the network epsilon-greedy for ``mode`` (with
        ``exploration.around: prior``, the prior's option epsilon-greedy)."""
        if network is None:
            return self.demonstrator
        explore = self.explore if self.options is None else self.explore_option
        exploring = lambda mask: explore(mask) if self.rng.random() < epsilon else None   # noqa: E731
        if self.exploration.around == 'prior':
            if self.options is None or self.prior is None:
                raise ValueError('exploration around the prior needs options and the prior measured')
            return PriorDriver(self.prior, self.options, mode, explore=exploring)
        return PolicyDriver(LearningQ(network, self.encoded, self.shield, self.planner), self.options, mode,
                            explore=exploring)

    def episode(self, seed: int, network: GraphQNetwork | None = None, mode: Mode | None = None,
                epsilon: float = 0.0, on_decision: OnDecision | None = None) -> list[Transition]:
        """One episode, by the demonstrator (``network`` None) or epsilon-greedy on ``network``'s
        Q values for ``mode``; returns its transitions."""
        driver, env = self.driver(network, mode, epsilon), self.env
        accumulator = EpisodeAccumulator(self.multi_step, self.gamma)
        transitions: list[Transition] = []
        state: dict = {}

        def on_start() -> None:
            state.update(record=self.decision_state(), rows=env.graph.row_of())

        def on_step(decision: StepDecision, info: dict, terminated: bool, truncated: bool) -> None:
            own, shared = info['reward_vector']
            emitted = accumulator.add(self.record(state['record'], state['rows'], decision, own, shared))
            if terminated or truncated:
                emitted += accumulator.finish(self.decision_state(final=True), terminated)
            else:
                state.update(record=self.decision_state(), rows=env.graph.row_of())
            transitions.extend(emitted)
            if on_decision is not None:
                on_decision(emitted)

        play_episode(env, driver, seed, on_step, on_start)
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

    def explore_option(self, mask: np.ndarray) -> int:
        """A random allowed option."""
        return int(self.rng.choice(np.flatnonzero(mask)))

    def decision_state(self, final: bool = False) -> DecisionRecord:
        """The state of the next decision, as the replay keeps it: the encoded graph and, over
        options, each CAV row's option mask (on the grid the decision gives its masks). The
        ``final`` state of an episode (for bootstrapping) has the masks its CAVs would choose
        under, and over options every row chooses anew there."""
        graph, snapshot, n = self.env.graph, self.env.sim.snapshot, self.env.graph.num_nodes
        observed = self.encoded(graph, snapshot)
        size = self.grid.size if self.options is None else self.options.size
        masks = np.zeros((n, size), bool)
        if self.options is not None:
            for row in graph.cav_rows():
                masks[row] = self.options.mask(snapshot.by_id[graph.vehicle_ids[row]])
        elif final:
            for row in graph.cav_rows():
                vehicle = snapshot.by_id[graph.vehicle_ids[row]]
                mask = self.shield.mask(vehicle, snapshot)
                masks[row] = self.planner.restrict(vehicle, mask) if self.planner is not None else mask
        choosing = np.ones(n, bool) if self.options is not None and final else None
        return DecisionRecord(observed, np.full(n, NO_ACTION, np.int64), masks, choosing=choosing)

    def record(self, state: DecisionRecord, row_of: dict[str, int], decision: StepDecision, own: np.ndarray,
               shared: np.ndarray) -> DecisionRecord:
        """The decision taken in ``state`` (``row_of``: its graph's rows): each CAV row's action
        (on the grid with the mask it chose under; over options the option it holds, and whether
        it began it here)."""
        masks = state.masks   # made for this decision alone (``decision_state``)
        actions = np.full(len(state.actions), NO_ACTION, np.int64)
        for vehicle_id, action in decision.actions.items():
            actions[row_of[vehicle_id]] = action
            if self.options is None:
                masks[row_of[vehicle_id]] = decision.masks[vehicle_id]
        choosing = None
        if self.options is not None:
            choosing = np.zeros(len(actions), bool)
            choosing[[row_of[vehicle_id] for vehicle_id in decision.began]] = True
        return DecisionRecord(state.graph, actions, masks, own, shared, choosing)
