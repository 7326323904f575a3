"""Collection on Ray actors, one learner (the Ape-X shape; issue 38): ``train --actors N``.

Each of the N actors is one Ray actor process with its own libsumo simulation, one torch thread,
its own random stream (exploration) and its own exploration rate (actor i of N at
epsilon^(1 + spread * i / (N - 1)), config/training.yaml ``actors.epsilon_spread``). An actor plays
whole training episodes with the collector every training run uses (``collecting.Collector``,
which plays the one episode loop, ``driving.episode``) on the network weights it was last sent,
and returns the episode's transitions (with their initial priorities set by the learner's replay
as it takes them) and metrics. The learner takes finished episodes in the order they finish, makes
``updates_per_decision`` updates per decision they hold (as the in-process loop does), and puts
its weights in the object store every ``broadcast_every`` updates; an actor loads them before its
next episode. Checkpoints, validation and candidates are the trainer's, as without actors.

An actor whose process dies is restarted by Ray (``max_restarts``) and given its episode again;
past the limit it is dropped and the others go on. Local Ray on loopback by default, a running
cluster with ``--address``.
"""
from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from exit_decision.config import ActionSpaceName, ProjectConfig
from exit_decision.driving.prior import PriorTable
from exit_decision.errors import UsageError
from exit_decision.learning.collecting import method_collector
from exit_decision.model.modes import Mode


def check_address(address: str) -> None:
    """UsageError, within seconds, unless something listens at ``address`` (host:port of a Ray
    head; ``auto``: the cluster ``ray start`` left on this machine, checked by Ray itself)."""
    if address == 'auto':
        return
    host, _, port = address.rpartition(':')
    try:
        socket.create_connection((host or '127.0.0.1', int(port)), timeout=5).close()
    except (OSError, ValueError):
        raise UsageError(f'--address {address}: no Ray cluster listening there (host:port of a head started '
                         f'with `ray start --head`, or auto)') from None


def start_ray(address: str | None, workers: int, package_root: Path) -> None:
    """Connect to a Ray cluster at ``address``, or start a local one of ``workers`` CPUs that
    listens on loopback only (no dashboard, no usage report). UsageError, within seconds, for an
    ``address`` with nothing listening."""
    if address is not None:
        check_address(address)
        if os.environ.get('RAY_AUTH_TOKEN') or os.environ.get('RAY_AUTH_TOKEN_PATH') or \
                (Path.home() / '.ray' / 'auth_token').is_file():
            # `ray start --head` (Ray >= 2.5x) turns token authentication on and writes the token
            # there; a driver joining uses it unless told otherwise (docs/training.md)
            os.environ.setdefault('RAY_AUTH_MODE', 'token')
    loopback = address is None or address.rpartition(':')[0] in ('127.0.0.1', 'localhost')
    if loopback:
        # read by ray at import: a Ray on this machine's loopback (a local address is not replaced
        # by the machine's network address; the servers bind 127.0.0.1 with _node_ip_address)
        os.environ['RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'] = '0'
        os.environ['RAY_USAGE_STATS_ENABLED'] = '0'
    import ray

    if address is None:
        # workers import this same copy of the package (a source tree before its install)
        path = os.pathsep.join(filter(None, [str(package_root), os.environ.get('PYTHONPATH', '')]))
        # 'local': a Ray of its own even when `ray start` left a cluster on this machine (None
        # would join that one, and refuse num_cpus)
        ray.init(address='local', num_cpus=workers, include_dashboard=False, log_to_driver=False,
                 _node_ip_address='127.0.0.1', runtime_env={'env_vars': {'PYTHONPATH': path}})
    else:
        ray.init(address=address, log_to_driver=False, **({'_node_ip_address': '127.0.0.1'} if loopback else {}))


class CollectingActor:
    """One actor's simulation and collector (made remote by ``ActorPool``)."""

    def __init__(self, config: ProjectConfig, algorithm: str, env_mode: str, action_space: ActionSpaceName,
                 shape: dict, seed: int, index: int, prior: dict | None = None):
        import torch

        from exit_decision.model.networks import GraphQNetwork, NetworkShape
        torch.set_num_threads(1)
        self.collector = method_collector(config, algorithm, env_mode, action_space,
                                          np.random.default_rng([seed, index]),
                                          None if prior is None else PriorTable.from_metadata(prior))
        self.network = GraphQNetwork(NetworkShape(**shape))
        self.version = -1

    def pid(self) -> int:
        return os.getpid()

    def episode(self, seed: int, weights: list, version: int, mode: Mode, epsilon: float) -> dict:
        """One training episode on the weights of ``version`` (``weights``: [their object ref],
        fetched only when the version is new)."""
        import ray
        if version != self.version:
            self.network.load_state_dict(ray.get(weights[0]))
            self.version = version
        decisions, started = [0], time.perf_counter()

        def count(transitions: list) -> None:
            decisions[0] += 1
        transitions = self.collector.episode(seed, self.network, mode, epsilon, on_decision=count)
        return {'transitions': transitions, 'metrics': self.collector.env.episode_log.metrics(),
                'decisions': decisions[0], 'version': version, 'seconds': time.perf_counter() - started}


@dataclass
class Finished:
    """An episode an actor finished, as the learner takes it."""
    actor: int
    epsilon: float
    result: dict


@dataclass
class PoolCounts:
    restarts: int = 0                      # episodes given again after their actor's process died
    dropped: list[int] = field(default_factory=list)   # actors past their restart limit
    errors: list[str] = field(default_factory=list)    # what each death raised


class ActorPool:
    """N collecting actors kept busy: ``episodes(next_task)`` yields each finished episode;
    ``broadcast(state_dict)`` sends new weights."""

    def __init__(self, config: ProjectConfig, algorithm: str, env_mode: str, action_space: ActionSpaceName,
                 shape: dict, seed: int, count: int, address: str | None, prior: dict | None = None):
        import exit_decision
        start_ray(address, count, Path(exit_decision.__file__).resolve().parent.parent)
        import ray
        settings = config.training.of_method(algorithm).actors
        self.spread = settings.epsilon_spread
        remote = ray.remote(num_cpus=1, max_restarts=settings.max_restarts, max_task_retries=0)(CollectingActor)
        self.actors = [remote.remote(config, algorithm, env_mode, action_space, shape, seed, index, prior)
                       for index in range(count)]
        self.counts = PoolCounts()
        self.version, self.weights = -1, None
        self.updates_at: dict[int, int] = {}   # version -> the learner's updates when it was sent

    def broadcast(self, state_dict: dict, updates: int) -> None:
        """The learner's weights, made after ``updates`` updates, for every actor's next episode."""
        import ray
        self.version += 1
        self.weights = [ray.put({key: value.detach().clone() for key, value in state_dict.items()})]
        self.updates_at[self.version] = updates

    def epsilon(self, index: int, base: float) -> float:
        """Actor ``index``'s exploration rate at the schedule's ``base`` (Ape-X's spread)."""
        n = len(self.actors)
        return float(base ** (1.0 + self.spread * index / (n - 1))) if n > 1 else base

    def pids(self) -> list[int]:
        import ray
        return ray.get([actor.pid.remote() for actor in self.actors])

    def episodes(self, next_task) -> Iterator[Finished]:
        """Keeps every live actor on an episode: ``next_task()`` gives (seed, mode, epsilon of the
        schedule) or None when no more may start; yields each episode as it finishes, until none
        is running. An actor gets its next episode before its last is yielded, on the weights of
        the last broadcast: collection and learning overlap (Ape-X's actors do not wait either).
        The episode of an actor that died goes to it again once Ray restarted it, or, past its
        restart limit, to the next free actor."""
        import ray
        running: dict = {}
        idle = list(range(len(self.actors)))
        requeued: list[tuple] = []   # the episodes of dropped actors, for the next free one

        def start(index: int, task: tuple) -> None:
            seed, mode, base = task
            epsilon = self.epsilon(index, base)
            ref = self.actors[index].episode.remote(seed, self.weights, self.version, mode, epsilon)
            running[ref] = (index, task, epsilon)

        def feed() -> None:
            while idle:
                task = requeued.pop(0) if requeued else next_task()
                if task is None:
                    return
                start(idle.pop(0), task)

        feed()
        while running:
            ready, _ = ray.wait(list(running), num_returns=1)
            index, task, epsilon = running.pop(ready[0])
            try:
                result = ray.get(ready[0])
            except ray.exceptions.RayActorError as error:
                self.counts.errors.append(f'actor {index}: {type(error).__name__}')
                if self._restarted(index):
                    self.counts.restarts += 1
                    start(index, task)
                    continue
                self.counts.dropped.append(index)
                requeued.append(task)
                feed()
                if not running:
                    raise RuntimeError('every actor died past actors.max_restarts') from None
                continue
            idle.append(index)
            feed()   # its next episode starts now: it plays while the learner learns from this one
            yield Finished(index, epsilon, result)

    def _restarted(self, index: int, timeout: float = 120.0) -> bool:
        """Wait for Ray to restart actor ``index`` after its process died: True once it answers
        again, False when it is dead for good (past ``max_restarts``) or silent past ``timeout``."""
        import ray
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                ray.get(self.actors[index].pid.remote(), timeout=10)
                return True
            except ray.exceptions.ActorUnavailableError:
                time.sleep(0.5)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                return False
        return False

    def close(self) -> None:
        import ray
        ray.shutdown()
