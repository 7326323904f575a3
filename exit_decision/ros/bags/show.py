"""``exit-decision show BAG``: a bag's episodes as time-space diagrams and bird's-eye clips.

Reads the vehicle states, the graphs, the commands (with their mode), the shield's overrides
and the episode events of a recorded bag through ``bags.read_messages``, rebuilds each
episode's frames with the same ``FrameBuilder`` as the visualizer node, and renders them with
``visualization.figures``. A bag recorded before the overrides had a topic shows none; one
without episode events (or cut before an episode's end) has its crashes inferred only.
"""
from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from exit_decision.config import ProjectConfig
from exit_decision.errors import UsageError
from exit_decision.ros.bags.storage import BagError, open_bag, read_messages
from exit_decision.ros.topics import COMMANDS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC
from exit_decision.ros.messages.conversions import (MessageError, commands_from_msg, graph_from_msg, overrides_from_msg,
                                                    states_from_msg)
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import VehicleState
from exit_decision.visualization.figures import TimeSpace, render_episode
from exit_decision.visualization.layout import RoadLayout
from exit_decision.visualization.trace import EpisodeTrace, FrameBuilder

TOPICS = {STATES_TOPIC, GRAPH_TOPIC, COMMANDS_TOPIC, OVERRIDES_TOPIC, EPISODE_TOPIC}
#: within one step: its states, the graph of them, the decision's commands and overrides (an
#: episode's start comes before its first step, its end after its last)
STEP_ORDER = {EPISODE_TOPIC: 0, STATES_TOPIC: 1, GRAPH_TOPIC: 2, COMMANDS_TOPIC: 3, OVERRIDES_TOPIC: 4}
LONG_BAG = 5000   # messages: a bag this long gets a progress bar (about 5 s of reading)


@dataclass
class Shown:
    trace: EpisodeTrace
    diagram: TimeSpace
    clips: list[Path]

    def summary(self) -> str:
        frames = self.trace.frames
        d = self.diagram
        switches = ', '.join(f'{a} -> {b} at {t:.1f} s' for t, a, b in d.mode_switches) or 'none'
        counted = '' if self.trace.collisions is None else f' (the bridge counted {self.trace.collisions} collision(s))'
        return (f'episode {self.trace.episode}: {len(d.trajectories)} vehicles, {len(frames)} steps '
                f'({frames[0].time:.1f}-{frames[-1].time:.1f} s), {d.collisions} crashed vehicle(s){counted}, '
                f'{d.lane_changes} CAV lane change(s) ({d.sumo_lane_changes} by SUMO\'s driver), '
                f'{d.overrides} shield override(s), mode switches: {switches}\n  '
                + '\n  '.join(str(p) for p in [self.diagram.path, *self.clips]))


def message_count(bag: Path) -> int:
    """Messages of the topics ``show`` reads; a bag that cannot be read is the user's to fix."""
    try:
        reader = open_bag(bag)
    except BagError as error:
        raise UsageError(str(error)) from None
    counts = {c.topic: c.msgcount for c in reader.connections}
    reader.close()
    if not counts.get(STATES_TOPIC):
        raise UsageError(f'{bag}: no {STATES_TOPIC} messages; show needs the vehicle states')
    return sum(n for topic, n in counts.items() if topic in TOPICS)


def on_road(vehicles: list[VehicleState], layout: RoadLayout) -> list[VehicleState]:
    """``vehicles``, if every lane they use is on the config's road (else the bag is from another road)."""
    for vehicle in vehicles:
        if vehicle.on_highway and not 0 <= vehicle.lane_index < layout.lane_count:
            raise MessageError(f'vehicle {vehicle.vehicle_id} is in lane {vehicle.lane_index}, the road of the '
                               f'config has {layout.lane_count} lanes (give --config-dir the bag was recorded with)')
    return vehicles


def read_traces(bag: Path, layout: RoadLayout, highway_edges: Collection[str], episodes: set[int] | None = None,
                progress: bool = True) -> dict[int, EpisodeTrace]:
    """The frames of each episode of the bag (of ``episodes`` only, if given); a message that
    does not fit (or a lane the config's road lacks) is the user's to fix, named in one line.
    ``highway_edges``: the config's highway sections (any other edge is a ramp)."""
    total = message_count(bag)
    builders: dict[int, FrameBuilder] = {}
    traces: dict[int, EpisodeTrace] = {}
    seen: set[int] = set()
    wanted = []
    for index, (topic, _, _, msg) in enumerate(tqdm(read_messages(bag, TOPICS), total=total, desc=bag.name, unit='msg',
                                                    disable=not progress or total < LONG_BAG, mininterval=0.5)):
        seen.add(msg.episode)
        if episodes is None or msg.episode in episodes:
            step = msg.step if topic != EPISODE_TOPIC else -1 if msg.event == msg.EVENT_STARTED else math.inf
            wanted.append((msg.episode, step, STEP_ORDER[topic], index, topic, msg))
    # in the order of the simulation, not the bag's: the recorder writes each topic's messages in
    # batches, so a decision's commands may follow the states of tens of steps after it
    for *_, topic, msg in sorted(wanted, key=lambda item: item[:4]):
        try:
            if topic == STATES_TOPIC:
                builder = builders.get(msg.episode)
                if builder is None:
                    builder = builders[msg.episode] = FrameBuilder(layout, msg.step_length, msg.episode)
                    traces[msg.episode] = EpisodeTrace(msg.episode, bag.name, msg.step_length)
                traces[msg.episode].frames.append(builder.add(msg.step, on_road(states_from_msg(msg, highway_edges), layout)))
            elif msg.episode in builders:
                if topic == COMMANDS_TOPIC:
                    builders[msg.episode].decide(commands_from_msg(msg), msg.mode, msg.step)
                elif topic == OVERRIDES_TOPIC:
                    builders[msg.episode].shield(overrides_from_msg(msg), msg.step)
                elif topic == EPISODE_TOPIC:
                    if msg.event == msg.EVENT_ENDED:
                        traces[msg.episode].collisions = builders[msg.episode].end(msg.p_collision)
                else:
                    graph = graph_from_msg(msg)
                    builders[msg.episode].graph(graph.vehicle_ids, graph.adjacency)
        except MessageError as error:
            raise UsageError(f'{bag}: {topic} of episode {msg.episode}, step {msg.step}: {error}') from error
    missing = sorted((episodes or set()) - set(traces))
    if missing:
        raise UsageError(f'--episode {missing[0]}: not in {bag}; episodes in it: '
                         f'{", ".join(map(str, sorted(seen)))}')
    return traces


def show_bag(bag: Path, config: ProjectConfig, out_dir: Path | None = None, *, episode: int | None = None,
             start: float | None = None, end: float | None = None, speed: float = 5.0, fps: float = 10.0,
             progress: bool = True) -> list[Shown]:
    """Write ``episode_<n>_time_space.png`` and ``episode_<n>_birds_eye.gif`` (+ .mp4) for each
    episode of the bag (or ``episode``), cut to [start, end] seconds of simulation time."""
    if start is not None and end is not None and start >= end:
        raise UsageError(f'--start {start:g} / --end {end:g}: the window is empty (start must be before end)')
    road = config.scenario.road
    layout = RoadLayout.of(RoadGeometry.of(road), road)
    traces = read_traces(bag, layout, road.names.sections, None if episode is None else {episode}, progress)
    out_dir = out_dir or bag.parent / f'{bag.name}_show'
    shown = []
    for number, trace in sorted(traces.items()):
        window = trace.window(start, end)
        if not window.frames:
            raise UsageError(f'--start/--end: episode {number} has no step between {start} and {end} s '
                             f'(it runs {trace.frames[0].time:.1f}-{trace.frames[-1].time:.1f} s)')
        diagram, clips = render_episode(window, layout, out_dir, f'episode_{number}', speed=speed, fps=fps,
                                        progress=progress)
        shown.append(Shown(window, diagram, clips))
    return shown
