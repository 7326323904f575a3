"""``evaluate --show N``: the first N episodes of each evaluation run, drawn without ROS.

The evaluation loop hands each episode's steps (exact collisions included), the commands of
each decision and the CAVs the shield overrode to an ``EpisodeRecorder``; at the end of the episode
it writes the same time-space diagram and bird's-eye clip as ``exit-decision show``.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from exit_decision.shield_overrides import ShieldOverride
from exit_decision.traffic import CavCommand, StepResult
from exit_decision.visualization.layout import RoadLayout
from exit_decision.visualization.trace import EpisodeTrace, FrameBuilder


@dataclass(frozen=True)
class ShowEpisodes:
    """Render the first ``episodes`` episodes of a run into ``out_dir`` as ``<label>_seed<seed>_*``."""
    out_dir: Path
    episodes: int
    label: str = 'run'
    mode: str = ''

    def named(self, label: str, mode: str = '') -> ShowEpisodes:
        return replace(self, label=label, mode=mode)

    def recorder(self, index: int, seed: int) -> EpisodeRecorder | None:
        """A recorder for the run's ``index``-th episode, or None past the first ``episodes``."""
        if index >= self.episodes:
            return None
        return EpisodeRecorder(self.out_dir, f'{self.label}_seed{seed}', self.mode)


class EpisodeRecorder:
    def __init__(self, out_dir: Path, stem: str, mode: str = ''):
        self.out_dir, self.stem, self.mode = out_dir, stem, mode

    def start(self, env) -> None:
        """After ``env.reset``: the road of the env and the episode's first state."""
        scenario = env.config.scenario
        self.layout = RoadLayout.of(env.sim.geometry, scenario.road)
        self.builder = FrameBuilder(self.layout, scenario.step_length)
        self.builder.decide({}, self.mode or env.mode)
        self.overrides = 0
        self.trace = EpisodeTrace(0, self.stem, scenario.step_length)
        self.steps([env.sim.state])

    def decide(self, commands: Mapping[str, CavCommand], overrides: Mapping[str, ShieldOverride]) -> None:
        self.overrides += len(overrides)
        self.builder.decide(commands)
        self.builder.shield(overrides)

    def steps(self, results: Iterable[StepResult]) -> None:
        for result in results:
            collided = [vehicle_id for c in result.collisions for vehicle_id in (c.collider, c.victim)]
            self.trace.frames.append(self.builder.add(result.step, result.vehicles, collided, self.overrides))

    def finish(self) -> None:
        from exit_decision.visualization.figures import render_episode
        render_episode(self.trace, self.layout, self.out_dir, self.stem, progress=False)
