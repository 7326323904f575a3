"""Training of every learned method (SPEC sections 4 and 7), per mode or one mode-conditioned network.

A method (``config/training.yaml`` ``methods``: GQN, MDGQN and the other papers' baselines)
is a state encoder (``exit_decision.encoders``), a network shape and a loss (single or
double target, m steps, uniform or prioritized replay); this one loop trains them all.

The loop, per decision: Q values of the graph (one forward for all rows), then each CAV
chooses under the shield, front to back: epsilon-greedy, the random action biased towards
keeping the lane and a small acceleration; the env holds the actions for the decision
interval; the m-step accumulator emits transitions whose returns are reward *vectors*
(``exit_decision.reward``); gradient updates sample the agent's replay and, for a share of
the batch, the demonstrations of the neutral rule-based driver (DQfD's margin loss, its
weight decaying linearly and never switched off), and score each sampled transition under
mode weights: the run's mode, or for a mode-conditioned network (``mode='conditioned'``)
weights drawn afresh per transition from the configured modes and the simplex around them
(relabelling, as in conditioned multi-objective Q-learning). Each CAV row learns from its
own credit (its own terms plus an equal share of the rest) or, as an ablation, from the
paper's global reward.

Checkpoints are chosen on validation runs against the teacher on the same seeds: a
candidate's score is its smallest mean paired return gain over the teacher across the
validation modes, and only candidates within the safety targets in every mode qualify.
Validation runs in a second process (``validation.parallel``) while training goes on, so
both cores work.

Outputs in the run directory: ``training.csv`` (one row per episode), ``validation.csv``
(one row per candidate and mode), ``policy.pt`` (best), ``last.pt`` (resumable state),
``candidates/`` (checkpoints waiting for or done with validation), ``config.json``.
"""
from __future__ import annotations

import json
import multiprocessing
import shutil
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from exit_decision.actions import NO_ACTION
from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ActionSpaceName, ProjectConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.errors import PolicyError
from exit_decision.encoders import StateEncoder
from exit_decision.learning.agent import GraphQAgent, UpdateSettings
from exit_decision.learning.replay import (DecisionRecord, EpisodeAccumulator, PrioritizedSampler, ReplayBuffer,
                                           scored_rewards)
from exit_decision.learning.validation import ValidationTask, selection_score, validate_checkpoint
from exit_decision.model.names import CONDITIONED
from exit_decision.model.networks import NetworkShape
from exit_decision.model.policy import git_revision, greedy_decision, load_policy, q_values, save_policy
from exit_decision.reward import WEIGHT_INPUT_SIZE, weight_input, weights_of_input
from exit_decision.tables import append_row

DEMONSTRATION_SEED = 800_000
VALIDATION_SEED = 900_000
EPISODE_SEED_STRIDE = 1_000_000


@dataclass(frozen=True)
class SampledBatch:
    """One update's batch: the arrays the agent learns from, which rows are demonstrations,
    the importance weights (prioritized replay; None: uniform) and the replay indices drawn."""
    arrays: dict[str, np.ndarray]
    is_demo: np.ndarray
    importance: np.ndarray | None
    indices: np.ndarray


@dataclass
class TrainingState:
    episode: int = 0
    decisions: int = 0
    updates: int = 0
    best_score: float = -np.inf


class WeightSampler:
    """Mode weights for relabelling: one of the configured modes exactly, or a point of the
    simplex near one (Dirichlet around its decision weights, Beta around its incentive)."""

    def __init__(self, config: ProjectConfig, modes: list[str], exact_share: float, concentration: float,
                 rng: np.random.Generator):
        self.anchors = np.array([weight_input(config.mode(m)) for m in modes])
        self.exact_share, self.concentration, self.rng = exact_share, concentration, rng

    def sample(self, count: int) -> np.ndarray:
        anchors = self.anchors[self.rng.integers(len(self.anchors), size=count)]
        near = self.rng.random(count) >= self.exact_share
        if near.any():
            k = self.concentration
            decision = np.array([self.rng.dirichlet(k * a[:4] + 1e-3) for a in anchors[near]])
            incentive = np.array([self.rng.beta(k * a[4] + 1e-3, k * a[5] + 1e-3) for a in anchors[near]])
            anchors[near] = np.column_stack([decision, incentive, 1.0 - incentive])
        return anchors


class Trainer:
    def __init__(self, config: ProjectConfig, algorithm: str, mode: str, seed: int, out_dir: Path,
                 action_space: ActionSpaceName = 'grid'):
        """``algorithm``: a method of the training config (gqn, mdgqn, dqn, ...); ``action_space``:
        the 81-action grid or options (agents/options.py)."""
        # Small networks: one thread is as fast as two here, and two threads collapse (80x
        # slower, measured) as soon as anything else runs on the other core.
        torch.set_num_threads(1)
        self.config, self.algorithm, self.mode, self.seed = config, algorithm, mode, seed
        self.method = method = config.training.method(algorithm)
        self.training = t = config.training.of_method(algorithm)
        self.out_dir = out_dir
        self.conditioned = mode == CONDITIONED
        learning_reward = method.reward_variant or config.env.reward_variant
        if self.conditioned and config.reward(learning_reward).kind != 'matrix':
            raise ValueError(f'the conditioned network needs a matrix reward, not {learning_reward!r}')
        c = t.conditioning
        if not self.conditioned:
            config.mode(mode)   # an unknown mode fails here, naming the known ones
        self.validation_modes = list(c.validation_modes) if self.conditioned else [mode]
        # SGRL trains one CAV at a time (the others drive as humans); validation runs every CAV
        self.action_space = action_space
        self.env = ExitDecisionEnv(config, mode=self.validation_modes[0], single_agent=method.single_agent,
                                   learning_reward=method.reward_variant, action_space=action_space)
        self.options = self.env.options   # None on the grid
        num_actions = self.options.size if self.options is not None else self.env.actions.size
        # as published: the bare shield and no planner (the env's serve the teacher)
        self.grid = self.env.actions
        self.shield = self.env.shield if method.measures else self.env.shield.bare()
        self.planner = self.env.planner if method.measures else None
        self.rng = np.random.default_rng(seed)
        self.sampler = WeightSampler(config, list(c.modes), c.exact_share, c.concentration, self.rng) \
            if self.conditioned else None
        n, scenario = config.graph.max_vehicles, config.scenario
        self.encoder_settings = {'name': method.encoder, 'graph_features': self.env.graph_builder.num_features,
                                 'lane_count': scenario.road.lane_count,
                                 'speed_limit': scenario.road.highway_speed_limit}
        self.encoder = StateEncoder(**self.encoder_settings)
        net = method.network
        self.shape = NetworkShape(self.encoder.num_features, num_actions, tuple(net.encoder), net.gcn,
                                  tuple(net.head), WEIGHT_INPUT_SIZE if self.conditioned else 0, net.dueling,
                                  net.adjacency_input, n if net.adjacency_input else 0)
        self.agent = GraphQAgent(self.shape, UpdateSettings(
            method.double, t.learning_rate, t.tau, t.demonstrations.margin, t.gradient_clip), seed)
        self.multi_step = method.multi_step
        self.replay = ReplayBuffer(t.replay_size, n, self.shape.num_features, num_actions)
        self.priorities = PrioritizedSampler(t.replay_size, method.prioritized.alpha, method.prioritized.beta) \
            if method.prioritized else None
        self.demos = ReplayBuffer(max(1, 250 * t.demonstrations.episodes), n, self.shape.num_features,
                                  num_actions)
        self.demonstrator = RuleBasedDriver.for_env(self.env)
        self.state = TrainingState()

    # --- schedules --------------------------------------------------------------------------

    def progress(self, episodes: int, steps: int | None) -> float:
        """How far a schedule of ``episodes`` RL episodes (or, given, ``steps`` RL decisions) has run, 0..1."""
        if steps:
            return min(self.state.decisions / steps, 1.0)
        return min(self.state.episode / episodes, 1.0) if episodes else 1.0

    def epsilon(self) -> float:
        e = self.training.exploration
        fraction = self.progress(e.epsilon_decay_episodes, e.epsilon_decay_steps)
        return e.epsilon_start + (e.epsilon_end - e.epsilon_start) * fraction

    def margin_weight(self) -> float:
        d = self.training.demonstrations
        fraction = self.progress(d.margin_decay_episodes, d.margin_decay_steps)
        return d.margin_weight_start + (d.margin_weight_end - d.margin_weight_start) * fraction

    def budget_spent(self, episodes: int) -> bool:
        """The RL phase is over: ``episodes`` episodes, or the configured environment steps."""
        return self.progress(episodes, self.training.environment_steps) >= 1.0

    def episode_weights(self) -> np.ndarray | None:
        """The weights the policy acts for in a training episode (conditioned: drawn)."""
        return self.sampler.sample(1)[0] if self.conditioned else None

    # --- collecting ---------------------------------------------------------------------------

    def explore(self, mask: np.ndarray) -> int:
        """A random allowed action; biased: usually keep the lane, acceleration ~ N(0, std),
        the nearest allowed (a uniform random action changes lane 2 times in 3 and brakes)."""
        e, grid = self.training.exploration, self.grid
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

    def collect_episode(self, seed: int, demonstrate: bool, epsilon: float,
                        on_decision=None) -> list:
        """One episode by the demonstrator or the epsilon-greedy policy; returns its
        transitions. ``on_decision(transitions)`` is called after every decision (learning)."""
        if self.options is not None:
            return self.collect_option_episode(seed, demonstrate, epsilon, on_decision)
        env = self.env
        env.reset(seed=seed)
        accumulator = EpisodeAccumulator(self.multi_step, self.training.gamma)
        transitions = []
        keep = self.grid.index(0, 0.0)
        weights = None if demonstrate else self.episode_weights()
        while True:
            graph, snapshot = env.graph, env.sim.snapshot
            observed = self.encoder.encode(graph, snapshot)
            if demonstrate:
                decision = self.demonstrator.decide(graph, snapshot)
            else:
                q = q_values(self.agent.online, observed, weights)
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

    def collect_option_episode(self, seed: int, demonstrate: bool, epsilon: float, on_decision=None) -> list:
        """``collect_episode`` over options: the rows whose option ended choose (the
        demonstrator: the neutral style on the route's lane plan, the same for every mode; the
        policy: epsilon-greedy over the allowed options), every CAV row acts with the option it
        holds, and the low level makes the commands."""
        env, space = self.env, self.options
        _, info = env.reset(seed=seed)
        accumulator = EpisodeAccumulator(self.multi_step, self.training.gamma)
        transitions = []
        neutral = space.index('route', 'neutral')
        weights = None if demonstrate else self.episode_weights()
        while True:
            graph = env.graph
            observed = self.encoder.encode(graph, env.sim.snapshot)
            choosing, masks, held = info['choosing'], info['option_masks'], info['options']
            if demonstrate:
                chosen = np.full(graph.num_nodes, neutral)
            else:
                q = np.where(masks, q_values(self.agent.online, observed, weights), -np.inf)
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

    def decision_arrays(self, graph, decision) -> tuple[np.ndarray, np.ndarray]:
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

    # --- learning ---------------------------------------------------------------------------

    def sample(self) -> SampledBatch:
        """A batch from the agent's replay and the demonstrations, each transition scored
        under mode weights (the run's mode, or drawn per transition when conditioned)."""
        t = self.training
        demo_count = 0
        if len(self.demos):
            demo_count = round(t.batch_size * t.demonstrations.batch_share) if len(self.replay) else t.batch_size
        own_count = t.batch_size - demo_count
        parts, is_demo = [], []
        indices, importance = np.zeros(0, np.int64), np.ones(demo_count, np.float32)
        if own_count:
            if self.priorities is not None:
                indices, own_importance = self.priorities.sample(own_count, self.rng)
                importance = np.concatenate([own_importance, importance])
            else:
                indices = self.rng.integers(len(self.replay), size=own_count)
            parts.append(self.replay.sample(indices))
            is_demo.append(np.zeros(own_count, bool))
        if demo_count:
            parts.append(self.demos.sample(self.rng.integers(len(self.demos), size=demo_count)))
            is_demo.append(np.ones(demo_count, bool))
        batch = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        size = len(batch['discounts'])
        if self.conditioned:
            weights = self.sampler.sample(size)
            batch['weights'] = weights.astype(np.float32)
            multipliers = weights_of_input(weights)
        else:   # the learning reward's weights of the mode (a baseline's reward has no modes)
            multipliers = np.broadcast_to(self.env.learning_weights, (size, 4, 2))
        batch['rewards'] = scored_rewards(batch, multipliers, t.credit) * np.float32(t.reward_scale)
        del batch['returns'], batch['global_returns']
        return SampledBatch(batch, np.concatenate(is_demo), importance if self.priorities is not None else None,
                            indices)

    def learn_step(self) -> dict[str, float]:
        """One gradient update on a sampled batch; prioritized replay learns the new priorities."""
        sampled = self.sample()
        losses, errors = self.agent.update(sampled.arrays, sampled.is_demo, self.margin_weight(), sampled.importance)
        if self.priorities is not None and len(sampled.indices):
            self.priorities.update(sampled.indices, errors[:len(sampled.indices)])
        self.state.updates += 1
        return losses

    def train_steps(self, count: int) -> list[dict[str, float]]:
        if len(self.replay) < self.training.warmup_decisions:
            return []
        return [self.learn_step() for _ in range(count)]

    def pretrain(self) -> None:
        """DQfD's pre-training: updates on demonstrations alone."""
        d = self.training.demonstrations
        for _ in tqdm(range(d.pretrain_updates), desc='pre-training on demonstrations', unit='upd',
                      leave=False):
            self.learn_step()

    # --- validation and files -----------------------------------------------------------------

    def metadata(self) -> dict:
        c = self.config
        return {
            'algorithm': self.algorithm, 'paper': self.method.paper, 'encoder': self.encoder_settings,
            'mode': self.mode, 'seed': self.seed,
            'conditioned': self.conditioned, 'modes': self.validation_modes,
            'reward_variant': self.method.reward_variant or c.env.reward_variant, 'measures': self.method.measures,
            'feature_set': c.graph.feature_set,
            'num_nodes': c.graph.max_vehicles, 'num_features': self.shape.num_features,
            'decision_interval': c.env.decision_interval, 'action_grid': c.env.actions.model_dump(),
            'action_space': self.action_space, 'multi_step': self.multi_step, 'git_revision': git_revision(),
            **({'options': c.env.options.model_dump()} if self.options is not None else {}),
            'episode': self.state.episode, 'updates': self.state.updates,
            'training': c.training.model_dump(),
        }

    def validation_seeds(self) -> list[int]:
        return [VALIDATION_SEED + i for i in range(self.training.validation.episodes)]

    def save_candidate(self) -> Path:
        path = self.out_dir / 'candidates' / f'episode_{self.state.episode:05d}.pt'
        save_policy(path, self.agent.online, self.metadata())
        self.agent.online.train()
        return path

    def record_validation(self, path: Path, per_mode: dict[str, dict[str, float]]) -> None:
        """Log a candidate's validation; keep it as policy.pt if it is the best so far."""
        v = self.training.validation
        score = selection_score(per_mode, v.min_exit_rate, v.max_cav_collision_rate)
        episode = int(path.stem.split('_')[1])
        for mode, row in per_mode.items():
            append_row(self.out_dir / 'validation.csv', {'episode': episode, 'mode': mode, **row, 'score': score})
        if score > self.state.best_score:
            self.state.best_score = score
            shutil.copyfile(path, self.out_dir / 'policy.pt')

    def save_state(self) -> None:
        torch.save({'online': self.agent.online.state_dict(), 'target': self.agent.target.state_dict(),
                    'optimizer': self.agent.optimizer.state_dict(), 'state': vars(self.state).copy(),
                    'rng': self.rng.bit_generator.state, 'metadata': self.metadata()},
                   self.out_dir / 'last.pt')

    def load_state(self, path: Path) -> None:
        data = torch.load(path, map_location='cpu', weights_only=True)
        if data['metadata']['algorithm'] != self.algorithm or data['metadata']['mode'] != self.mode:
            raise ValueError(f'{path}: a {data["metadata"]["algorithm"]}/{data["metadata"]["mode"]} run, '
                             f'not {self.algorithm}/{self.mode}')
        self.agent.online.load_state_dict(data['online'])
        self.agent.target.load_state_dict(data['target'])
        self.agent.optimizer.load_state_dict(data['optimizer'])
        self.state = TrainingState(**data['state'])
        self.rng.bit_generator.state = data['rng']

    # --- the whole run ------------------------------------------------------------------------

    def load_network(self, path: Path) -> None:
        """Start from a policy checkpoint's network (online and target) instead of pre-training:
        a pre-trained policy fine-tuned under another setting (e.g. the lane planner)."""
        policy = load_policy(path)
        if policy.network.shape != self.shape:
            raise PolicyError(f'{path}: its network ({policy.network.shape}) is not this run\'s ({self.shape})')
        self.agent.online.load_state_dict(policy.network.state_dict())
        self.agent.target.load_state_dict(policy.network.state_dict())

    def run(self, episodes: int, resume: Path | None = None, progress: bool = True,
            init: Path | None = None) -> Path:
        """Demonstrations, pre-training (skipped when resuming or starting from ``init``'s
        network), then the RL episodes with validation, ``episodes`` of them or, when the config
        gives ``environment_steps``, as many as that budget takes; returns the kept policy.pt."""
        if resume is None and (self.out_dir / 'training.csv').exists():
            raise FileExistsError(f'{self.out_dir} holds an earlier run (training.csv): resume it with '
                                  f'--resume {self.out_dir / "last.pt"}, or choose another --out')
        self.out_dir.mkdir(parents=True, exist_ok=True)
        (self.out_dir / 'config.json').write_text(json.dumps(
            {'algorithm': self.algorithm, 'mode': self.mode, 'seed': self.seed, 'episodes': episodes,
             'init': None if init is None else str(init), 'config': self.config.model_dump()}, indent=2))
        clock = {'start': time.monotonic()}
        demo = self.training.demonstrations
        for i in tqdm(range(demo.episodes), desc='demonstrations', unit='ep', disable=not progress, leave=False):
            for transition in self.collect_episode(DEMONSTRATION_SEED + i, demonstrate=True, epsilon=0.0):
                self.demos.add(transition)
        if resume is not None:
            self.load_state(resume)
        elif init is not None:
            self.load_network(init)
        clock['demonstrations'] = time.monotonic()
        if resume is None and init is None and len(self.demos):
            self.pretrain()
        clock['pretraining'] = time.monotonic()
        if demo.pretrain_updates or init is not None:   # a network that learnt already is fine-tuned
            self.agent.set_learning_rate(self.training.fine_tune_learning_rate)
        task = ValidationTask(self.config, self.validation_modes, self.validation_seeds(), self.action_space)
        with Validator(task, self.training.validation.parallel, self.env) as validator:
            if self.state.episode == 0:
                validator.submit(self.save_candidate())   # the pre-trained policy is a candidate too
            steps = self.training.environment_steps
            bar = tqdm(total=steps or episodes, initial=self.state.decisions if steps else self.state.episode,
                       desc=f'train {self.algorithm}/{self.mode}', unit='step' if steps else 'ep',
                       disable=not progress)
            while not self.budget_spent(episodes):
                before = self.state.decisions
                metrics = self.train_episode()
                bar.update(self.state.decisions - before if steps else 1)
                bar.set_postfix(p_CAV=f'{metrics["p_CAV"]:.2f}', col=f'{metrics["p_collision_CAV"]:.2f}',
                                best=f'{self.state.best_score:.3g}')
                for path, per_mode in validator.finished():
                    self.record_validation(path, per_mode)
                if self.state.episode % self.training.validation.every_episodes == 0 or self.budget_spent(episodes):
                    validator.submit(self.save_candidate())
                    self.save_state()
            bar.close()
            for path, per_mode in validator.finished(wait=True):
                self.record_validation(path, per_mode)
        self.save_state()
        self.env.close()
        self.write_timing(clock, 'resumed: this invocation only' if resume is not None else
                          f'demonstrations, RL and validation; network from {init}, not pre-trained'
                          if init is not None else 'demonstrations, pre-training, RL and validation')
        return self.out_dir / 'policy.pt'

    def write_timing(self, clock: dict[str, float], note: str) -> None:
        """timing.json: wall time of the run's phases (this invocation; a resumed run's own), and
        the RL episodes and decisions of the run."""
        end = time.monotonic()
        (self.out_dir / 'timing.json').write_text(json.dumps({
            'demonstrations_s': clock['demonstrations'] - clock['start'],
            'pretraining_s': clock['pretraining'] - clock['demonstrations'],
            'rl_s': end - clock['pretraining'], 'total_s': end - clock['start'], 'episodes': self.state.episode,
            'decisions': self.state.decisions, 'note': note},
            indent=2))

    def train_episode(self) -> dict[str, float]:
        """One training episode with learning after every decision; one row of training.csv
        (returned)."""
        epsilon = self.epsilon()
        losses: list[dict[str, float]] = []

        def learn(transitions: list) -> None:
            for transition in transitions:
                index = self.replay.add(transition)
                if self.priorities is not None:
                    self.priorities.added(index)
            self.state.decisions += 1
            losses.extend(self.train_steps(self.training.updates_per_decision))
        self.collect_episode(self.seed * EPISODE_SEED_STRIDE + self.state.episode, demonstrate=False,
                             epsilon=epsilon, on_decision=learn)
        metrics = self.env.episode_log.metrics()
        row = {'episode': self.state.episode, 'epsilon': epsilon, 'margin_weight': self.margin_weight(),
               'loss': float(np.mean([x['loss'] for x in losses])) if losses else float('nan'),
               'td_loss': float(np.mean([x['td_loss'] for x in losses])) if losses else float('nan'),
               'decisions': self.state.decisions, 'updates': self.state.updates, **metrics}
        append_row(self.out_dir / 'training.csv', row)
        self.state.episode += 1
        return row


class Validator:
    """Runs candidate validations in a second process (or inline), in submission order."""

    def __init__(self, task: ValidationTask, parallel: bool, env: ExitDecisionEnv):
        self.task, self.env = task, env   # env: the trainer's, for inline validation
        self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) if parallel else None
        self.pending: list[tuple[Path, Future | dict]] = []

    def __enter__(self) -> Validator:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)

    def submit(self, path: Path) -> None:
        if self.pool is None:
            single, self.env.sim.single_agent = self.env.sim.single_agent, False   # validated driving every CAV
            try:
                self.pending.append((path, validate_checkpoint(self.task, path, self.env)))
            finally:
                self.env.sim.single_agent = single
        else:
            self.pending.append((path, self.pool.submit(validate_checkpoint, self.task, path)))

    def finished(self, wait: bool = False) -> list[tuple[Path, dict]]:
        done = []
        while self.pending:
            path, result = self.pending[0]
            if isinstance(result, Future):
                if not (wait or result.done()):
                    break
                result = result.result()
            done.append((path, result))
            self.pending.pop(0)
        return done
