"""visualizer: the scene as ``visualization_msgs/MarkerArray`` on /exit_decision/markers (frame ``map``).

Thin glue around ``exit_decision.visualization``: vehicle states, the graph, the commands
(with their mode), the options CAVs hold (a policy over options), the CAVs the shield overrode, the decision node's shield-override counter
(/diagnostics) and the bridge's episode events go into a ``FrameBuilder``; ``MarkerScene``
says what to draw and what to delete. At most ``max_rate`` arrays per wall-clock second (a
synchronous stack steps much faster than anyone watches): frames in between still count for
collisions, a frame with no vehicles is always sent, and the newest frame held back is sent
when the rate allows (so the last one is never lost). At an episode's end the status text
gets the bridge's collision count. Open the topic (or a recorded bag) in RViz or Foxglove
with fixed frame ``map``.

As the other nodes, it starts an episode's frames at the first states of an episode the
bridge's (or the player's) EVENT_STARTED announced, and only then, takes a states message
only if it can follow the current episode and step (``StepGate``; as an onlooker it follows
any later step of the episode, so one joining mid-episode or falling behind draws on) and
every field fits the scenario (``states_cdr.checked_states_cdr``), and otherwise rejects it
whole and counts it on /diagnostics: a bad message changes no frame.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray
from exit_decision_msgs.msg import (CavCommandArray, CavOptionArray, EpisodeEvent, ShieldOverrideArray,
                                    TrafficGraph, VehicleStateArray)
from geometry_msgs.msg import Point
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from exit_decision.input_checks import StateLimits, StepGate
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import run_node
from exit_decision.ros.intake import Intake
from exit_decision.ros.parameters import declare, declare_config, declare_cpu_affinity, describe, follow
from exit_decision.ros.take import LAST_STEP
from exit_decision.ros.topics import (COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, EVENT_QOS, GRAPH_TOPIC,
                                      MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_QOS, STATES_TOPIC,
                                      STREAM_QOS)
from exit_decision.ros.messages.conversions import (MessageError, commands_from_msg, graph_from_msg, options_from_msg,
                                                    overrides_from_msg)
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.visualization.layout import RoadLayout
from exit_decision.visualization.markers import FRAME_ID, MarkerScene, MarkerSpec
from exit_decision.visualization.trace import Frame, FrameBuilder


def marker_array(specs: Sequence[MarkerSpec], stamp, reuse: dict | None = None) -> MarkerArray:
    """MarkerSpecs as the ROS message. ``reuse``: the Marker messages of earlier calls, per
    (namespace, id), refilled in place: constructing a Marker (a dozen sub-messages) was half of
    a frame's cost (3.8 of 8 ms for 76 markers; serialising is the other half)."""
    markers = []
    for spec in specs:
        marker = reuse.get(spec.key) if reuse is not None else None
        if marker is None:
            marker = Marker()
            marker.header.frame_id = FRAME_ID
            if reuse is not None:
                reuse[spec.key] = marker
        marker.ns, marker.id, marker.text = spec.namespace, spec.marker_id, spec.text
        marker.type, marker.action = getattr(Marker, spec.kind), getattr(Marker, spec.action)
        marker.header.stamp = stamp
        position, orientation, scale, colour = marker.pose.position, marker.pose.orientation, marker.scale, marker.color
        position.x, position.y, position.z = map(float, spec.position)
        orientation.z, orientation.w = math.sin(spec.yaw / 2), math.cos(spec.yaw / 2)
        scale.x, scale.y, scale.z = map(float, spec.scale)
        colour.r, colour.g, colour.b, colour.a = map(float, spec.colour)
        marker.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in spec.points]
        markers.append(marker)
    return MarkerArray(markers=markers)


class Visualizer(Node):
    def __init__(self):
        super().__init__('visualizer')
        config = declare_config(self)
        declare_cpu_affinity(self)
        self.max_rate = declare(self, 'max_rate', 20.0, describe(
            '[Hz] most marker arrays per wall-clock second; 0: one per vehicle-state message; applies at once',
            float_range=(0.0, 1000.0)))
        follow(self, 'max_rate')
        road = config.scenario.road
        geometry = RoadGeometry.of(road)
        layout = RoadLayout.of(geometry, road)
        self.limits = StateLimits.of(config, geometry)
        # an onlooker: any step later in the episode follows (one joining mid-episode, or behind
        # and dropping, goes on drawing); only a step back, or one of another episode, is refused
        self.gate = StepGate(config.scenario.max_steps, max_gap=config.scenario.max_steps + 1)
        self.frames = FrameBuilder(layout, config.scenario.step_length)
        self.scene = MarkerScene(layout)
        self.overrides: int | None = None
        self.last_sent = -math.inf
        self.last: tuple[Frame, object] | None = None      # the newest frame and its stamp
        self.held_back: tuple[Frame, object] | None = None   # ... if the rate limit kept it back
        self.trailing = None                                # the one-shot timer that sends it
        self.markers: dict = {}   # Marker messages reused frame to frame (marker_array)
        self.publisher = self.create_publisher(MarkerArray, MARKERS_TOPIC, STREAM_QOS)
        self.diagnostics = Diagnostics(self, 'visualizer')
        intake = Intake.of_config(self, self.diagnostics, config)
        # events first: when an episode's start and its first states are both waiting, the
        # node's wait (executor.Waiter) empties the queue of the subscription created first first
        self.events = intake.subscribe(EpisodeEvent, EPISODE_TOPIC, self.on_episode, EVENT_QOS)
        # the nodes' depth, 1000 (at most 1000 x the states' size limit, 18 MB for N = 60): behind for a
        # while under a flood from several publishers, it would lose messages no counter can see
        # (rclpy says no message's publisher), its own stream's among them
        intake.subscribe(VehicleStateArray, STATES_TOPIC, self.on_states, STATES_QOS, raw=True)
        frames = self.frames

        def draw_graph(msg: TrafficGraph) -> None:
            graph = graph_from_msg(msg)
            frames.graph(graph.vehicle_ids, graph.adjacency)

        for kind, topic, counter, what, use in (
                (CavCommandArray, COMMANDS_TOPIC, 'commands', 'commands',
                 lambda msg: frames.decide(commands_from_msg(msg), msg.mode, msg.step)),
                (TrafficGraph, GRAPH_TOPIC, 'graphs', 'graph', draw_graph),
                (ShieldOverrideArray, OVERRIDES_TOPIC, 'shield_overrides', 'shield overrides',
                 lambda msg: frames.shield(overrides_from_msg(msg), msg.step)),
                (CavOptionArray, OPTIONS_TOPIC, 'options', 'options', lambda msg: frames.options(options_from_msg(msg)))):
            refuse = self.other_episode(topic, what)
            intake.subscribe(kind, topic, self.of_this_episode(topic, counter, what, use, refuse), STREAM_QOS,
                             window=self.episode_window, refuse=refuse)
        intake.subscribe(DiagnosticArray, DIAGNOSTICS_TOPIC, self.on_diagnostics, STREAM_QOS)

    def on_states(self, raw: bytes) -> None:
        states = self.diagnostics.take_states(raw, self.gate, self.events, self.limits)
        if states is None:
            return
        step, vehicles = states.step, states.vehicles
        if self.gate.begins(states.episode, step):
            self.frames.reset(states.episode)
        self.gate.accept(states.episode, step)
        frame = self.frames.add(step, vehicles, overrides=self.overrides)
        self.last = frame, states.stamp
        wait = self.last_sent + 1.0 / self.max_rate - time.monotonic() if self.max_rate and vehicles else 0.0
        if wait <= 0:
            self.send(frame, states.stamp)
            return
        if self.held_back is not None:
            self.scene.observe(self.held_back[0])   # replaced unsent: its episode and collisions still count
        self.held_back = self.last
        if self.trailing is None:
            self.trailing = self.create_timer(wait, self.send_held_back, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def send(self, frame: Frame, stamp) -> None:
        """Publish a frame's markers (after a frame held back before it was taken in)."""
        if self.held_back is not None and self.held_back[0] is not frame:
            self.scene.observe(self.held_back[0])
        self.held_back = None
        self.last_sent = time.monotonic()
        self.publisher.publish(marker_array(self.scene.update(frame), stamp, self.markers))
        self.diagnostics.count('marker_arrays')

    def send_held_back(self) -> None:
        """(Wall-clock one-shot) the newest frame the rate limit kept back, once the rate allows."""
        self.destroy_timer(self.trailing)
        self.trailing = None
        if self.held_back is not None:
            self.send(*self.held_back)

    def on_episode(self, msg: EpisodeEvent) -> None:
        """A start is announced to the gate (the episode's frames begin with its first states); at
        the end of the shown episode: its last frame again, with the bridge's collision count."""
        if msg.event == EpisodeEvent.EVENT_STARTED:
            if self.gate.episode is None:
                self.frames.reset(msg.episode)   # the gate follows its first episode at once
            self.gate.announce(msg.episode)
            return
        if msg.event != EpisodeEvent.EVENT_ENDED or msg.episode != self.frames.episode or self.last is None:
            return
        if self.held_back is not None:
            self.send(*self.held_back)
        frame, stamp = self.last
        self.send(dataclasses.replace(frame, crashed=(), collisions=self.frames.end(msg.p_collision)), stamp)

    def episode_window(self) -> tuple[int, int, int] | None:
        """The episode drawn, any step (None before the first): the intake drops a message of
        another episode on its header, before it is decoded (``Intake.subscribe``)."""
        episode = self.frames.episode
        return None if episode is None else (episode, 0, LAST_STEP)

    def other_episode(self, topic: str, what: str) -> Callable[[int, int, int], None]:
        """The refusal of ``amount`` messages of ``topic`` of another episode than the one drawn
        (``out_of_sequence``), said with the episode of one of them."""
        def refuse(episode: int, step: int, amount: int = 1) -> None:
            self.diagnostics.drop(topic, 'out_of_sequence', f'{what} of episode {episode}',
                                  f'not the episode drawn, {self.frames.episode}', amount)
        return refuse

    def of_this_episode(self, topic: str, counter: str, what: str, use: Callable[[object], None],
                        refuse: Callable[[int, int, int], None]) -> Callable[[object], None]:
        """A subscription's callback: ``use(msg)`` for a message of the episode drawn; one of
        another episode is refused (``other_episode``), one that does not fit the scenario is
        counted under ``counter`` (``invalid``); neither changes anything."""
        def callback(msg) -> None:
            if msg.episode != self.frames.episode:
                refuse(msg.episode, msg.step)
                return
            try:
                use(msg)
            except MessageError as error:
                self.diagnostics.reject(counter, f'{what} of step {msg.step}', str(error), topic)
        return callback

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == 'decision_node':
                for value in status.values:
                    if value.key == 'shield_overrides':
                        self.overrides = int(float(value.value))


def main() -> int:
    return run_node('visualizer', Visualizer)


if __name__ == '__main__':
    raise SystemExit(main())
