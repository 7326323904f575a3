"""Frames of an episode: the vehicles of a step with what the stack decided around them.

``FrameBuilder`` is fed step by step (by the visualizer node from topics, by ``show`` from a
bag, by ``evaluate --show`` from the environment): it holds each CAV's last command, the
shield's override of that command if there was one, and the active mode, and finds
collisions. SUMO removes colliding vehicles (``collision.action remove``), so where no exact
list is given (topics and bags carry none per step), a vehicle that left before the end of
its route is taken as crashed, at its last state; the bridge's episode-end event gives the
exact count (``FrameBuilder.end``), which a bag or a live stack has once the episode ends.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from exit_decision.agents.options import CavOption
from exit_decision.shield_overrides import ShieldOverride
from exit_decision.traffic import CavCommand, VehicleState
from exit_decision.visualization.layout import RoadLayout

ARRIVAL_MARGIN = 1.0   # [m] beyond one step of travel: a vehicle this close to its route's end arrived


@dataclass(frozen=True)
class Frame:
    episode: int
    step: int
    time: float                                   # [s] simulation time
    vehicles: Sequence[VehicleState]
    commands: Mapping[str, CavCommand]            # each controlled CAV's last command (held)
    mode: str                                     # '' until the first commands
    crashed: Sequence[VehicleState] = ()          # last states of vehicles removed by a collision
    edges: Sequence[tuple[str, str]] = ()         # graph edges between vehicle ids (no self loops)
    overrides: int | None = None                  # shield overrides so far, where known
    overridden: Mapping[str, ShieldOverride] = field(default_factory=dict)      # held commands the shield chose
    new_overrides: Mapping[str, ShieldOverride] = field(default_factory=dict)   # arrived since the previous frame
    collisions: int | None = None                 # the bridge's count, on a frame after the episode's end
    options: Mapping[str, str] = field(default_factory=dict)   # a policy over options: each CAV's, 'intent style'


@dataclass
class EpisodeTrace:
    """The frames of one episode (or a time window of it) and what the clip is called."""
    episode: int
    label: str
    step_length: float
    frames: list[Frame] = field(default_factory=list)
    collisions: int | None = None     # collisions the bridge counted in the episode, where known

    def window(self, start: float | None, end: float | None) -> EpisodeTrace:
        frames = [f for f in self.frames if (start is None or f.time >= start) and (end is None or f.time <= end)]
        return EpisodeTrace(self.episode, self.label, self.step_length, frames, self.collisions)

    def vehicle_classes(self) -> dict[str, str]:
        return {v.vehicle_id: v.vehicle_class for frame in self.frames for v in frame.vehicles}


class FrameBuilder:
    def __init__(self, layout: RoadLayout, step_length: float, episode: int = 0):
        self.layout, self.step_length = layout, step_length
        self.reset(episode)

    def reset(self, episode: int) -> None:
        self.episode = episode
        self.mode = ''
        self.step = -1
        self.held: dict[str, CavCommand] = {}
        self.held_options: dict[str, str] = {}
        self.decided_at: dict[str, int] = {}                          # vehicle id -> step of its last command
        self.overridden: dict[str, tuple[int, ShieldOverride]] = {}   # vehicle id -> (step, override)
        self.new_overrides: dict[str, ShieldOverride] = {}
        self.previous: dict[str, VehicleState] = {}
        self.cav_ids: set[str] = set()
        self.edges: list[tuple[str, str]] = []

    def decide(self, commands: Mapping[str, CavCommand], mode: str | None = None, step: int | None = None) -> None:
        """Commands of a decision at ``step`` (default: the last frame's), shown from the next frame on."""
        step = self.step if step is None else step
        self.held.update(commands)
        for vehicle_id in commands:
            self.decided_at[vehicle_id] = step
            if self.overridden.get(vehicle_id, (step,))[0] < step:
                del self.overridden[vehicle_id]   # an override of an earlier decision
        if mode:
            self.mode = mode

    def shield(self, overrides: Mapping[str, ShieldOverride], step: int | None = None) -> None:
        """The shield's overrides of the decision at ``step`` (default: the last frame's), before
        or after its commands; those of an older decision than a CAV's last command are ignored."""
        step = self.step if step is None else step
        for vehicle_id, override in overrides.items():
            if step >= self.decided_at.get(vehicle_id, step):
                self.overridden[vehicle_id] = (step, override)
                self.new_overrides[vehicle_id] = override

    def options(self, options: Mapping[str, CavOption]) -> None:
        """The options the CAVs hold at the newest decision (a policy over options)."""
        self.held_options.update({vid: f'{o.option.lane_intent} {o.option.style}' for vid, o in options.items()})

    def end(self, p_collision: float) -> int | None:
        """The bridge's collision count of the episode from its end event (collisions per CAV),
        or None where it does not say (no CAV seen)."""
        return round(p_collision * len(self.cav_ids)) if self.cav_ids and math.isfinite(p_collision) else None

    def graph(self, vehicle_ids: Sequence[str], adjacency) -> None:
        """The newest graph: its edges are drawn between the vehicles of the next frames."""
        rows = np.argwhere(np.triu(np.asarray(adjacency), 1))
        self.edges = [(vehicle_ids[i], vehicle_ids[j]) for i, j in rows if vehicle_ids[i] and vehicle_ids[j]]

    def crashed(self, vehicles: Sequence[VehicleState]) -> list[VehicleState]:
        """Vehicles of the previous frame that are gone though their route did not end there."""
        present = {v.vehicle_id for v in vehicles}
        crashed = []
        for vehicle_id, last in self.previous.items():
            if vehicle_id in present:
                continue
            if self.layout.route_end(last) - last.position > last.speed * self.step_length + ARRIVAL_MARGIN:
                crashed.append(last)
        return crashed

    def add(self, step: int, vehicles: Sequence[VehicleState], collided: Iterable[str] | None = None,
            overrides: int | None = None) -> Frame:
        """The frame of a step; ``collided``: the ids of this step's collisions where they are
        known exactly (the environment), else they are found from departures."""
        if collided is None:
            crashed = self.crashed(vehicles)
        else:
            crashed = [self.previous[i] for i in sorted(set(collided)) if i in self.previous]
        present = {v.vehicle_id for v in vehicles}
        commanded = {v.vehicle_id for v in vehicles if v.controlled}   # a released CAV takes no more commands
        self.held = {k: c for k, c in self.held.items() if k in commanded}
        self.overridden = {k: o for k, o in self.overridden.items() if k in commanded}
        self.held_options = {k: o for k, o in self.held_options.items() if k in commanded}
        frame = Frame(self.episode, step, step * self.step_length, list(vehicles), dict(self.held), self.mode,
                      crashed, [e for e in self.edges if e[0] in present and e[1] in present], overrides,
                      {k: o for k, (_, o) in self.overridden.items()}, self.new_overrides,
                      options=dict(self.held_options))
        self.new_overrides = {}
        self.step = step
        self.previous = {v.vehicle_id: v for v in vehicles}
        self.cav_ids.update(v.vehicle_id for v in vehicles if v.is_cav)
        return frame
