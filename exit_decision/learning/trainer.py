"""Training of every learned method (docs/design.md, "Learning" and "The other papers' methods"),
per mode or one mode-conditioned network.

A method (``config/training.yaml`` ``methods``: GQN, MDGQN and the other papers' baselines)
is a state encoder (``exit_decision.encoders``), a network shape and a loss (single or
double target, m steps, uniform or prioritized replay); this one loop trains them all.

``Trainer`` keeps the schedule and the loop: demonstrations of the neutral rule-based driver,
DQfD's pre-training on them, then RL episodes (``collecting``) with gradient updates after
every decision on batches of the agent's replay and the demonstrations (``sampling``; DQfD's
margin loss, its weight decaying linearly and never switched off; a mode-conditioned network,
``mode='conditioned'``, learns from transitions relabelled with drawn mode weights), epsilon
and the margin weight decaying over episodes or environment steps.

Checkpoints are chosen on validation runs against the teacher on the same seeds
(``validation``): a candidate's score is its smallest mean paired return gain over the teacher
across the validation modes, and only candidates within the safety targets in every mode
qualify; validation runs in a second process while training goes on.

Outputs in the run directory: ``training.csv`` (one row per episode), ``validation.csv``
(one row per candidate and mode), ``policy.pt`` (best), ``last.pt`` (resumable state),
``candidates/`` (checkpoints waiting for or done with validation), ``config.json``,
``timing.json`` (``checkpoints``).
"""
from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from exit_decision.config import ActionSpaceName, ProjectConfig
from exit_decision.driving.prior import PriorTable
from exit_decision.learning.actors import ActorPool
from exit_decision.learning.agent import GraphQAgent, UpdateSettings
from exit_decision.learning.checkpoints import Checkpoints, TrainingState, run_description
from exit_decision.learning.collecting import method_collector
from exit_decision.learning.sampling import Experience, WeightSampler
from exit_decision.learning.validation import (ValidationTask, Validator, record_validation, unvalidated_candidates,
                                               validated_scores, validation_seeds)
from exit_decision.model.modes import Mode, ModeWeights
from exit_decision.model.names import CONDITIONED
from exit_decision.model.networks import NetworkShape
from exit_decision.reward import WEIGHT_INPUT_SIZE
from exit_decision.tables import append_row

DEMONSTRATION_SEED = 800_000
EPISODE_SEED_STRIDE = 1_000_000


class Trainer:
    """One run of a method for a mode (or the conditioned network): the schedules (epsilon, the
    margin weight, the budget) and the loop; its parts collect, sample, checkpoint and validate."""

    def __init__(self, config: ProjectConfig, algorithm: str, mode: str, seed: int, out_dir: Path,
                 action_space: ActionSpaceName = 'grid'):
        """``algorithm``: a method of the training config (gqn, mdgqn, dqn, ...); ``action_space``:
        the 81-action grid or options (agents/options.py)."""
        # Small networks: one thread is as fast as two here, and two threads collapse (80x
        # slower, measured) as soon as anything else runs on the other core.
        torch.set_num_threads(1)
        self.config, self.algorithm, self.mode, self.seed = config, algorithm, mode, seed
        self.modes = ModeWeights(config)
        method = config.training.method(algorithm)
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
        #: a per-mode run's mode, every episode's (a conditioned run draws one per episode)
        self.own_mode = None if self.conditioned else self.modes.mode(mode)
        # SGRL trains one CAV at a time (the others drive as humans); validation runs every CAV
        self.action_space = action_space
        self.rng = np.random.default_rng(seed)
        self.collector = method_collector(config, algorithm, self.validation_modes[0], action_space, self.rng)
        self.env = env = self.collector.env
        num_actions = env.options.size if env.options is not None else env.actions.size
        self.sampler = WeightSampler(config, list(c.modes), c.exact_share, c.concentration, self.rng) \
            if self.conditioned else None
        n = config.graph.max_vehicles
        encoder = self.collector.encoded.encoder
        net = method.network
        self.shape = NetworkShape(encoder.num_features, num_actions, tuple(net.encoder), net.gcn,
                                  tuple(net.head), WEIGHT_INPUT_SIZE if self.conditioned else 0, net.dueling,
                                  net.adjacency_input, n if net.adjacency_input else 0)
        self.agent = GraphQAgent(self.shape, UpdateSettings(
            method.double, t.learning_rate, t.tau, t.demonstrations.margin, t.gradient_clip), seed)
        self.experience = Experience(t, method.prioritized, n, self.shape.num_features, num_actions, self.sampler,
                                     env.learning_weights, self.rng)
        self.checkpoints = Checkpoints(out_dir, run_description(
            config, algorithm, mode, seed, action_space, encoder.settings, self.validation_modes,
            self.shape.num_features), self.agent, self.rng)
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

    def episode_mode(self) -> Mode:
        """The mode the policy acts for in a training episode (conditioned: weights drawn)."""
        return self.modes.of_weights(self.sampler.sample(1)[0]) if self.conditioned else self.own_mode

    # --- learning ---------------------------------------------------------------------------

    def learn_step(self) -> dict[str, float]:
        """One gradient update on a sampled batch; prioritized replay learns the new priorities."""
        sampled = self.experience.sample()
        losses, errors = self.agent.update(sampled.arrays, sampled.is_demo, self.margin_weight(), sampled.importance)
        self.experience.learned(sampled, errors)
        self.state.updates += 1
        return losses

    def train_steps(self, count: int) -> list[dict[str, float]]:
        if len(self.experience.replay) < self.training.warmup_decisions:
            return []
        return [self.learn_step() for _ in range(count)]

    def pretrain(self) -> None:
        """DQfD's pre-training: updates on demonstrations alone."""
        d = self.training.demonstrations
        for _ in tqdm(range(d.pretrain_updates), desc='pre-training on demonstrations', unit='upd',
                      leave=False):
            self.learn_step()

    # --- the whole run ------------------------------------------------------------------------

    def run(self, episodes: int, resume: Path | None = None, progress: bool = True,
            init: Path | None = None, actors: int = 0, address: str | None = None) -> Path:
        """Demonstrations, pre-training (skipped when resuming or starting from ``init``'s
        network), then the RL episodes with validation, ``episodes`` of them or, when the config
        gives ``environment_steps``, as many as that budget takes; returns the kept policy.pt.
        ``actors``: collect the RL episodes on that many Ray actors (``actors``; 0: here), on the
        cluster at ``address`` (None: a local Ray)."""
        if resume is None and (self.out_dir / 'training.csv').exists():
            raise FileExistsError(f'{self.out_dir} holds an earlier run (training.csv): resume it with '
                                  f'--resume {self.out_dir / "last.pt"}, or choose another --out')
        self.out_dir.mkdir(parents=True, exist_ok=True)
        (self.out_dir / 'config.json').write_text(json.dumps(
            {'algorithm': self.algorithm, 'mode': self.mode, 'action_space': self.action_space, 'seed': self.seed,
             'episodes': episodes,
             'init': None if init is None else str(init), 'config': self.config.model_dump()}, indent=2))
        clock = {'start': time.monotonic()}
        demo = self.training.demonstrations
        for i in tqdm(range(demo.episodes), desc='demonstrations', unit='ep', disable=not progress, leave=False):
            for transition in self.collector.episode(DEMONSTRATION_SEED + i):
                self.experience.demos.add(transition)
        if resume is not None:
            self.state = self.checkpoints.load_state(resume)
            # validations recorded after last.pt was written count too (policy.pt may hold a later one)
            self.state.best_score = max([self.state.best_score, *validated_scores(self.out_dir).values()])
        elif init is not None:
            self.checkpoints.load_network(init)
        clock['demonstrations'] = time.monotonic()
        if resume is None and init is None and len(self.experience.demos):
            self.pretrain()
        clock['pretraining'] = time.monotonic()
        if demo.pretrain_updates or init is not None:   # a network that learnt already is fine-tuned
            self.agent.set_learning_rate(self.training.fine_tune_learning_rate)
        validation = self.training.validation
        seeds = validation_seeds(validation.episodes)
        styles = None
        if self.action_space == 'options':   # the prior every checkpoint carries (driving.prior)
            styles = self.use_prior(seeds, progress)
        elif 'prior' in (self.training.bootstrap, self.training.exploration.around):
            raise ValueError('bootstrap and exploration around the prior need --action-space options')
        task = ValidationTask(self.config, self.validation_modes, seeds, self.action_space, styles)
        with Validator(task, validation.parallel, self.env) as validator:
            if self.state.episode == 0:
                validator.submit(self.checkpoints.save_candidate(self.state))   # the pre-trained policy too
            for path in unvalidated_candidates(self.out_dir) if resume is not None else ():
                validator.submit(path)   # saved by the run resumed, which stopped before validating them
            steps = self.training.environment_steps
            bar = tqdm(total=steps or episodes, initial=self.state.decisions if steps else self.state.episode,
                       desc=f'train {self.algorithm}/{self.mode}', unit='step' if steps else 'ep',
                       disable=not progress)
            source = self.episodes_on_actors(episodes, self.actor_pool(actors, address)) if actors else \
                self.episodes_here(episodes)
            first, started = (self.state.episode, self.state.decisions, self.state.updates), time.monotonic()
            for metrics in source:
                bar.update(self.state.decisions - bar.n if steps else 1)
                postfix = {'p_CAV': f'{metrics["p_CAV"]:.2f}', 'col': f'{metrics["p_collision_CAV"]:.2f}',
                           'best': f'{self.state.best_score:.3g}'}
                if actors:
                    elapsed = max(time.monotonic() - started, 1e-9)
                    done = [now - then for now, then in zip((self.state.episode, self.state.decisions,
                                                             self.state.updates), first)]
                    postfix.update({'ep/s': f'{done[0] / elapsed:.2f}', 'dec/s/actor': f'{done[1] / elapsed / actors:.0f}',
                                    'upd/s': f'{done[2] / elapsed:.0f}', 'age': metrics['weights_age']})
                bar.set_postfix(postfix)
                self.record(validator.finished())
                if self.state.episode % validation.every_episodes == 0 or self.budget_spent(episodes):
                    validator.submit(self.checkpoints.save_candidate(self.state))
                    self.checkpoints.save_state(self.state)
            bar.close()
            self.record(validator.finished(wait=True))
        self.checkpoints.save_state(self.state)
        self.env.close()
        self.checkpoints.write_timing(clock, self.state, 'resumed: this invocation only' if resume is not None else
                                      f'demonstrations, RL and validation; network from {init}, not pre-trained'
                                      if init is not None else 'demonstrations, pre-training, RL and validation')
        return self.out_dir / 'policy.pt'

    def use_prior(self, seeds: list[int], progress: bool) -> dict[str, list[dict]]:
        """Measure the prior on the validation seeds: every checkpoint carries it; with
        ``bootstrap: prior`` the targets bootstrap on its option, with ``exploration.around:
        prior`` the episodes explore around it. Returns the constant options' episodes it was
        measured from (validation chooses its best fixed drivers from them)."""
        from exit_decision.evaluation.evaluate import constant_option_episodes, prior_of
        single, self.env.sim.single_agent = self.env.sim.single_agent, False   # every CAV drives the style
        try:
            by_style = constant_option_episodes(self.env, seeds, desc='the prior' if progress else None)
        finally:
            self.env.sim.single_agent = single
        self.set_prior(prior_of(self.env, by_style))
        return by_style

    def set_prior(self, prior: PriorTable) -> None:
        """Use ``prior``, measured already (``use_prior``; ``bench learning --actors`` measures it
        once for all its runs): every checkpoint carries it, the episodes explore around it and the
        targets bootstrap on it as the config says."""
        self.checkpoints.description['prior'] = prior.to_metadata()
        self.collector.prior = prior
        if self.training.bootstrap == 'prior':
            options = prior.option_indices(self.env.options)
            self.experience.prior_actions = lambda multipliers: options[prior.best_indices(multipliers)]

    def record(self, validated: list[tuple[Path, dict]]) -> None:
        """Log finished validations; the best candidate so far becomes policy.pt."""
        for path, per_mode in validated:
            self.state.best_score = record_validation(self.out_dir, path, per_mode, self.training.validation,
                                                      self.state.best_score)

    def train_episode(self) -> dict[str, float]:
        """One training episode in this process, with learning after every decision; one row of
        training.csv (returned)."""
        epsilon = self.epsilon()
        losses: list[dict[str, float]] = []

        def learn(transitions: list) -> None:
            for transition in transitions:
                self.experience.add(transition)
            self.state.decisions += 1
            losses.extend(self.train_steps(self.training.updates_per_decision))
        self.collector.episode(self.seed * EPISODE_SEED_STRIDE + self.state.episode, self.agent.online,
                               self.episode_mode(), epsilon, on_decision=learn)
        return self.finish_episode(epsilon, losses, self.env.episode_log.metrics())

    def finish_episode(self, epsilon: float, losses: list[dict[str, float]], metrics: dict[str, float],
                       **columns) -> dict[str, float]:
        """The episode's row of training.csv (returned), and the episode counted."""
        row = {'episode': self.state.episode, 'epsilon': epsilon, 'margin_weight': self.margin_weight(),
               'loss': float(np.mean([x['loss'] for x in losses])) if losses else float('nan'),
               'td_loss': float(np.mean([x['td_loss'] for x in losses])) if losses else float('nan'),
               'decisions': self.state.decisions, 'updates': self.state.updates, **columns, **metrics}
        append_row(self.out_dir / 'training.csv', row)
        self.state.episode += 1
        return row

    def episodes_here(self, episodes: int) -> Iterator[dict[str, float]]:
        """Training episodes in this process until the budget is spent: their rows."""
        while not self.budget_spent(episodes):
            yield self.train_episode()

    def actor_pool(self, count: int, address: str | None) -> ActorPool:
        """``count`` Ray actors (``actors``) that collect this run's episodes, on the cluster at
        ``address`` (None: a local Ray); they play with the prior when it was measured before."""
        return ActorPool(self.config, self.algorithm, self.validation_modes[0], self.action_space,
                         self.shape.to_dict(), self.seed, count, address, self.checkpoints.description.get('prior'))

    def episodes_on_actors(self, episodes: int, pool: ActorPool) -> Iterator[dict[str, float]]:
        """Training episodes on the actors of ``pool`` (``actor_pool``; closed at the end) until the
        budget is spent; the learner here learns from each as it finishes, ``updates_per_decision``
        updates per decision, and broadcasts its weights every ``actors.broadcast_every`` updates."""
        broadcast_every = self.training.actors.broadcast_every
        dispatched = [self.state.episode]

        def next_task() -> tuple | None:
            if self.budget_spent(episodes) or (not self.training.environment_steps and dispatched[0] >= episodes):
                return None
            seed = self.seed * EPISODE_SEED_STRIDE + dispatched[0]
            dispatched[0] += 1
            return seed, self.episode_mode(), self.epsilon()

        try:
            pool.broadcast(self.agent.online.state_dict(), self.state.updates)
            for finished in pool.episodes(next_task):
                result = finished.result
                age = self.state.updates - pool.updates_at[result['version']]
                for transition in result['transitions']:
                    self.experience.add(transition)
                self.state.decisions += result['decisions']
                losses = self.train_steps(result['decisions'] * self.training.updates_per_decision)
                if self.state.updates - pool.updates_at[pool.version] >= broadcast_every:
                    pool.broadcast(self.agent.online.state_dict(), self.state.updates)
                yield self.finish_episode(finished.epsilon, losses, result['metrics'], actor=finished.actor,
                                          weights_age=age, actor_seconds=result['seconds'])
        finally:
            self.actor_counts = pool.counts
            pool.close()
