"""Training of one decision mode with GQN or MDGQN (SPEC section 4), with its measures.

The loop, per decision: Q values of the graph (one forward for all rows), then each CAV
chooses under the shield, front to back: epsilon-greedy, the random action biased towards
keeping the lane and a small acceleration; the env holds the actions for the decision
interval; the m-step accumulator emits transitions; gradient updates sample the agent's
replay and, for a share of the batch, the demonstrations of the rule-based driver (with
DQfD's margin loss, its weight decaying linearly and never switched off). Every few episodes
a greedy validation run scores the policy; the best one is kept as ``policy.pt``.

Outputs in the run directory: ``training.csv`` (one row per episode: reward, loss, epsilon,
metrics), ``validation.csv``, ``policy.pt`` (best), ``last.pt`` (resumable state),
``config.json`` (everything that made the run).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ProjectConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.evaluate import evaluate
from exit_decision.learning.agent import Algorithm, GraphQAgent, UpdateSettings
from exit_decision.learning.networks import NetworkShape
from exit_decision.learning.replay import NO_ACTION, DecisionRecord, EpisodeAccumulator, ReplayBuffer
from exit_decision.tables import append_row
from exit_decision.policy import GraphPolicy, PolicyController, git_revision, q_values, save_policy
from exit_decision.traffic import VehicleState

DEMONSTRATION_SEED = 800_000
VALIDATION_SEED = 900_000
EPISODE_SEED_STRIDE = 1_000_000


@dataclass
class TrainingState:
    episode: int = 0
    decisions: int = 0
    updates: int = 0
    best_score: float = -np.inf


class Trainer:
    def __init__(self, config: ProjectConfig, algorithm: Algorithm, mode: str, seed: int, out_dir: Path):
        # Small networks: one thread is as fast as two here, and two threads collapse (80x
        # slower, measured) as soon as anything else runs on the other core.
        torch.set_num_threads(1)
        self.config, self.algorithm, self.mode, self.seed = config, algorithm, mode, seed
        self.training = config.training
        self.out_dir = out_dir
        self.env = ExitDecisionEnv(config, mode=mode)
        self.grid, self.shield = self.env.actions, self.env.shield
        self.rng = np.random.default_rng(seed)
        t = self.training
        self.shape = NetworkShape(self.env.graph_builder.num_features, self.grid.size,
                                  t.network.encoder, t.network.gcn, t.network.head)
        self.agent = GraphQAgent(self.shape, UpdateSettings(
            algorithm, t.learning_rate, t.tau, t.demonstrations.margin, t.gradient_clip), seed)
        self.multi_step = t.algorithms[algorithm].multi_step
        n = config.graph.max_vehicles
        self.replay = ReplayBuffer(t.replay_size, n, self.shape.num_features, self.grid.size)
        self.demos = ReplayBuffer(max(1, 250 * t.demonstrations.episodes), n, self.shape.num_features,
                                  self.grid.size)
        self.demonstrator = RuleBasedDriver.for_env(self.env)
        self.state = TrainingState()

    # --- schedules --------------------------------------------------------------------------

    def epsilon(self) -> float:
        e = self.training.exploration
        fraction = min(self.state.episode / e.epsilon_decay_episodes, 1.0)
        return e.epsilon_start + (e.epsilon_end - e.epsilon_start) * fraction

    def margin_weight(self) -> float:
        d = self.training.demonstrations
        fraction = min(self.state.episode / d.margin_decay_episodes, 1.0)
        return d.margin_weight_start + (d.margin_weight_end - d.margin_weight_start) * fraction

    # --- acting -----------------------------------------------------------------------------

    def explore(self, mask: np.ndarray) -> int:
        """A random allowed action; biased: usually keep the lane, acceleration ~ N(0, std),
        the nearest allowed (a uniform random action changes lane 2 times in 3 and brakes)."""
        e, grid = self.training.exploration, self.grid
        if not e.biased:
            return int(self.rng.choice(np.flatnonzero(mask)))
        changes = [c for c in grid.lane_changes if (mask & (grid.lane_change_of == c)).any()]
        if 0 in changes and (len(changes) == 1 or self.rng.random() < e.keep_lane_probability):
            change = 0
        else:
            sides = [c for c in changes if c != 0] or changes
            change = sides[self.rng.integers(len(sides))]
        candidates = np.flatnonzero(mask & (grid.lane_change_of == change))
        wanted = self.rng.normal(0.0, e.acceleration_std)
        return int(candidates[np.argmin(np.abs(grid.acceleration_of[candidates] - wanted))])

    def run_episode(self, seed: int, demonstrate: bool, epsilon: float) -> list:
        """One episode; returns its transitions (for the demo buffer or the agent's replay),
        and trains along the way when not demonstrating."""
        env = self.env
        env.reset(seed=seed)
        accumulator = EpisodeAccumulator(self.multi_step, self.training.gamma)
        transitions, losses = [], []
        keep = self.grid.index(0, 0.0)
        while True:
            graph, vehicles = env.graph, env.sim.snapshot.vehicles
            if demonstrate:
                decision = self.demonstrator.decide(graph, vehicles)
            else:
                q = q_values(self.agent.online, graph)
                row_of = {vid: row for row, vid in enumerate(graph.vehicle_ids) if vid}

                def choose(vehicle: VehicleState, mask: np.ndarray) -> int:
                    if self.rng.random() < epsilon:
                        return self.explore(mask)
                    return int(np.where(mask, q[row_of[vehicle.vehicle_id]], -np.inf).argmax())
                decision = self.shield.decide(env.sim.snapshot, env.cav_ids(), choose)
            actions, masks = self.decision_arrays(graph, decision)
            _, reward, terminated, truncated, _ = env.step(np.where(actions >= 0, actions, keep))
            scaled = reward * self.training.reward_scale
            emitted = accumulator.add(DecisionRecord(graph, actions, masks, scaled))
            if terminated or truncated:
                emitted += accumulator.finish(self.final_record(), terminated)
            if demonstrate:
                transitions += emitted
            else:
                for transition in emitted:
                    self.replay.add(transition)
                self.state.decisions += 1
                losses += self.train_steps(self.training.updates_per_decision)
            if terminated or truncated:
                break
        self.last_losses = losses
        return transitions

    def decision_arrays(self, graph, decision) -> tuple[np.ndarray, np.ndarray]:
        n = graph.num_nodes
        actions = np.full(n, NO_ACTION, np.int64)
        masks = np.zeros((n, self.grid.size), bool)
        for row, vehicle_id in enumerate(graph.vehicle_ids):
            if vehicle_id in decision.actions:
                actions[row] = decision.actions[vehicle_id]
                masks[row] = decision.masks[vehicle_id]
        return actions, masks

    def final_record(self) -> DecisionRecord:
        """The last state, with the masks its CAVs would choose under (for bootstrapping)."""
        graph = self.env.graph
        snapshot = self.env.sim.snapshot
        masks = np.zeros((graph.num_nodes, self.grid.size), bool)
        for row in graph.cav_rows():
            masks[row] = self.shield.mask(snapshot.by_id[graph.vehicle_ids[row]], snapshot)
        return DecisionRecord(graph, np.full(graph.num_nodes, NO_ACTION, np.int64), masks)

    # --- learning ---------------------------------------------------------------------------

    def sample(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        t = self.training
        demo_count = 0
        if len(self.demos):
            demo_count = round(t.batch_size * t.demonstrations.batch_share) if len(self.replay) else t.batch_size
        own_count = t.batch_size - demo_count
        parts, is_demo = [], []
        if own_count:
            parts.append(self.replay.sample(self.rng.integers(len(self.replay), size=own_count)))
            is_demo.append(np.zeros(own_count, bool))
        if demo_count:
            parts.append(self.demos.sample(self.rng.integers(len(self.demos), size=demo_count)))
            is_demo.append(np.ones(demo_count, bool))
        batch = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        return batch, np.concatenate(is_demo)

    def train_steps(self, count: int) -> list[dict[str, float]]:
        if len(self.replay) < self.training.warmup_decisions:
            return []
        out = []
        for _ in range(count):
            batch, demo = self.sample()
            out.append(self.agent.update(batch, demo, self.margin_weight()))
            self.state.updates += 1
        return out

    def pretrain(self) -> None:
        """DQfD's pre-training: updates on demonstrations alone."""
        d = self.training.demonstrations
        for _ in tqdm(range(d.pretrain_updates), desc='pre-training on demonstrations', unit='upd',
                      leave=False):
            batch, demo = self.sample()
            self.agent.update(batch, demo, self.margin_weight())
            self.state.updates += 1

    # --- validation and files -----------------------------------------------------------------

    def metadata(self) -> dict:
        c = self.config
        return {
            'algorithm': self.algorithm, 'mode': self.mode, 'seed': self.seed,
            'reward_variant': c.env.reward_variant, 'feature_set': c.graph.feature_set,
            'num_nodes': c.graph.max_vehicles, 'num_features': self.shape.num_features,
            'decision_interval': c.env.decision_interval, 'action_grid': c.env.actions.model_dump(),
            'multi_step': self.multi_step, 'git_revision': git_revision(),
            'episode': self.state.episode, 'updates': self.state.updates,
            'training': c.training.model_dump(),
        }

    def validate(self) -> dict[str, float]:
        v = self.training.validation
        policy = GraphPolicy(self.out_dir / 'policy.pt', self.agent.online, self.metadata())
        result = evaluate(self.env, PolicyController(policy, self.shield),
                          [VALIDATION_SEED + i for i in range(v.episodes)], progress=False)
        self.agent.online.train()
        mean = {key: float(np.nanmean([e[key] for e in result.episodes])) for key in result.episodes[0]
                if key != 'seed'}
        mean['score'] = mean['p_CAV'] - v.collision_weight * mean['p_collision_CAV']
        return mean

    def validate_and_keep(self) -> None:
        """Validate; keep the policy if it is the best so far; save the resumable state."""
        result = self.validate()
        result['episode'] = self.state.episode
        append_row(self.out_dir / 'validation.csv', result)
        if result['score'] > self.state.best_score:
            self.state.best_score = result['score']
            save_policy(self.out_dir / 'policy.pt', self.agent.online, {**self.metadata(), 'validation': result})
        self.save_state()

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

    def run(self, episodes: int, resume: Path | None = None, progress: bool = True) -> Path:
        if resume is None and (self.out_dir / 'training.csv').exists():
            raise FileExistsError(f'{self.out_dir} holds an earlier run (training.csv): resume it with '
                                  f'--resume {self.out_dir / "last.pt"}, or choose another --out')
        self.out_dir.mkdir(parents=True, exist_ok=True)
        (self.out_dir / 'config.json').write_text(json.dumps(
            {'algorithm': self.algorithm, 'mode': self.mode, 'seed': self.seed, 'episodes': episodes,
             'config': self.config.model_dump()}, indent=2))
        demo = self.training.demonstrations
        for i in tqdm(range(demo.episodes), desc='demonstrations', unit='ep', disable=not progress, leave=False):
            for transition in self.run_episode(DEMONSTRATION_SEED + i, demonstrate=True, epsilon=0.0):
                self.demos.add(transition)
        if resume is not None:
            self.load_state(resume)
        elif len(self.demos):
            self.pretrain()
        self.agent.set_learning_rate(self.training.fine_tune_learning_rate)
        if self.state.episode == 0:
            self.validate_and_keep()   # the pre-trained policy is a candidate too
        bar = tqdm(total=episodes, initial=self.state.episode, desc=f'train {self.algorithm}/{self.mode}',
                   unit='ep', disable=not progress)
        while self.state.episode < episodes:
            epsilon = self.epsilon()
            self.run_episode(self.seed * EPISODE_SEED_STRIDE + self.state.episode, demonstrate=False,
                             epsilon=epsilon)
            metrics = self.env.episode_log.metrics()
            losses = self.last_losses
            row = {'episode': self.state.episode, 'epsilon': epsilon, 'margin_weight': self.margin_weight(),
                   'loss': float(np.mean([x['loss'] for x in losses])) if losses else float('nan'),
                   'td_loss': float(np.mean([x['td_loss'] for x in losses])) if losses else float('nan'),
                   'decisions': self.state.decisions, 'updates': self.state.updates, **metrics}
            append_row(self.out_dir / 'training.csv', row)
            self.state.episode += 1
            bar.update(1)
            bar.set_postfix(reward=f'{metrics["reward"]:.0f}', p_CAV=f'{metrics["p_CAV"]:.2f}',
                            col=f'{metrics["p_collision_CAV"]:.2f}')
            if self.state.episode % self.training.validation.every_episodes == 0 or self.state.episode == episodes:
                self.validate_and_keep()
        bar.close()
        self.env.close()
        return self.out_dir / 'policy.pt'
