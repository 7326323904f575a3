"""A frame as markers: plain descriptions of ``visualization_msgs/Marker`` (ROS-free).

``MarkerScene.update(frame)`` gives the markers to send for a frame: the road (lane
boundaries and ramps as line strips, edge names), each vehicle as a box sized by its length
and coloured by class with its id as text, the graph's edges, each CAV's last command (an
arrow forward, or into the target lane for a lane change, coloured by the acceleration),
the CAVs whose held command the shield chose instead of their driver's (an orange frame
around the box and a text: wanted -> given), collisions (a red disc and text, kept
``collision_hold`` seconds) and a text with the mode, time, shield overrides and, after the
episode's end, the bridge's collision count; then a DELETE for every marker of the previous update that is
gone (vehicles that left). A new episode starts with DELETEALL.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from exit_decision.shield_overrides import ShieldOverride
from exit_decision.visualization.layout import (
    CLASS_COLOURS,
    COLLISION_COLOUR,
    ROAD_COLOUR,
    VEHICLE_WIDTH,
    RoadLayout,
)
from exit_decision.visualization.trace import Frame

Colour = tuple[float, float, float, float]
Point = tuple[float, float, float]

FRAME_ID = 'map'
VEHICLE_HEIGHT = 1.5      # [m]
ARROW_LENGTH = 6.0        # [m] of a command arrow
EDGE_COLOUR: Colour = (0.55, 0.55, 0.55, 0.6)
TEXT_COLOUR: Colour = (0.1, 0.1, 0.1, 1.0)
OVERRIDE_COLOUR: Colour = (0.9, 0.4, 0.0, 1.0)
OVERRIDE_MARGIN = 0.8     # [m] of the orange frame around a CAV the shield overrode
ACCELERATION_RANGE = (-6.0, 3.0)   # [m/s^2] colour scale of command arrows: full red / full green there


@dataclass(frozen=True, slots=True)
class MarkerSpec:
    """The fields of a visualization_msgs/Marker that the scene uses."""
    namespace: str
    marker_id: int
    kind: str = 'CUBE'          # CUBE | ARROW | CYLINDER | LINE_STRIP | LINE_LIST | TEXT_VIEW_FACING
    action: str = 'ADD'         # ADD | DELETE | DELETEALL
    position: Point = (0.0, 0.0, 0.0)
    yaw: float = 0.0            # [rad] about z
    scale: Point = (1.0, 1.0, 1.0)
    colour: Colour = (1.0, 1.0, 1.0, 1.0)
    points: tuple[Point, ...] = ()
    text: str = ''

    @property
    def key(self) -> tuple[str, int]:
        return self.namespace, self.marker_id


def rgba(rgb: tuple[float, float, float], alpha: float = 1.0) -> Colour:
    return (*rgb, alpha)


def acceleration_colour(acceleration: float) -> Colour:
    """Red for braking, grey for holding speed, green for speeding up (full at ACCELERATION_RANGE's ends)."""
    low, high = ACCELERATION_RANGE
    share = min(acceleration / low, 1.0) if acceleration < 0 else min(acceleration / high, 1.0)
    grey = 0.6
    if acceleration < 0:
        return (grey + (0.85 - grey) * share, grey * (1 - share), grey * (1 - share), 1.0)
    return (grey * (1 - share), grey + (0.7 - grey) * share, grey * (1 - share), 1.0)


class MarkerScene:
    def __init__(self, layout: RoadLayout, collision_hold: float = 3.0):
        self.layout = layout
        self.collision_hold = collision_hold
        self.road = self.road_markers()
        self.ids: dict[str, int] = {}
        self.shown: set[tuple[str, int]] = set()
        self.collisions: list[tuple[float, int, float, float, str]] = []   # time, id, x, y, vehicle id
        self.collision_count = 0
        self.episode: int | None = None
        self.overrides_seen: int | None = None
        self.clear = False

    def road_markers(self) -> list[MarkerSpec]:
        markers = [MarkerSpec('road', i, 'LINE_STRIP', scale=(0.15, 0.0, 0.0), colour=rgba(ROAD_COLOUR),
                              points=tuple((x, y, 0.0) for x, y in points))
                   for i, (_, points) in enumerate(self.layout.lines())]
        markers += [MarkerSpec('road_names', i, 'TEXT_VIEW_FACING', position=(x, y, 0.0), scale=(0.0, 0.0, 3.0),
                               colour=TEXT_COLOUR, text=name)
                    for i, (name, x, y) in enumerate(self.layout.labels())]
        return markers

    def vehicle_id(self, vehicle_id: str) -> int:
        return self.ids.setdefault(vehicle_id, len(self.ids))

    def frame_markers(self, frame: Frame) -> list[MarkerSpec]:
        """Every marker of the frame (ADD), the road included."""
        markers = list(self.road)
        poses = {}
        for vehicle in frame.vehicles:
            pose = poses[vehicle.vehicle_id] = self.layout.place(vehicle)
            marker_id = self.vehicle_id(vehicle.vehicle_id)
            override = frame.overridden.get(vehicle.vehicle_id)
            if override is not None:   # before the box: drawn from above, the box covers the frame's middle
                markers += self.override_markers(marker_id, vehicle.length, pose, override)
            markers.append(MarkerSpec('vehicles', marker_id, 'CUBE', position=(pose.x, pose.y, VEHICLE_HEIGHT / 2),
                                      yaw=pose.yaw, scale=(vehicle.length, VEHICLE_WIDTH, VEHICLE_HEIGHT),
                                      colour=rgba(CLASS_COLOURS[vehicle.vehicle_class])))
            markers.append(MarkerSpec('vehicle_ids', marker_id, 'TEXT_VIEW_FACING',
                                      position=(pose.x, pose.y, VEHICLE_HEIGHT + 1.5), scale=(0.0, 0.0, 1.5),
                                      colour=TEXT_COLOUR, text=self.vehicle_label(frame, vehicle.vehicle_id)))
            command = frame.commands.get(vehicle.vehicle_id)
            if command is not None:
                markers.append(self.command_arrow(marker_id, vehicle.length, pose, command.lane_change,
                                                  command.acceleration))
        if frame.edges:
            points = []
            for a, b in frame.edges:
                points += [(poses[a].x, poses[a].y, 0.2), (poses[b].x, poses[b].y, 0.2)]
            markers.append(MarkerSpec('graph_edges', 0, 'LINE_LIST', scale=(0.1, 0.0, 0.0), colour=EDGE_COLOUR,
                                      points=tuple(points)))
        markers += self.collision_markers(frame)
        markers.append(self.status_text(frame))
        return markers

    @staticmethod
    def vehicle_label(frame: Frame, vehicle_id: str) -> str:
        """The id, and under it the option the CAV holds (a policy over options)."""
        option = frame.options.get(vehicle_id)
        return vehicle_id if option is None else f'{vehicle_id}\n{option}'

    def command_arrow(self, marker_id: int, length: float, pose, lane_change: int, acceleration: float) -> MarkerSpec:
        front_x = pose.x + math.cos(pose.yaw) * length / 2
        front_y = pose.y + math.sin(pose.yaw) * length / 2
        side = lane_change * self.layout.lane_spacing
        tip = (front_x + ARROW_LENGTH * math.cos(pose.yaw) - side * math.sin(pose.yaw),
               front_y + ARROW_LENGTH * math.sin(pose.yaw) + side * math.cos(pose.yaw), 1.0)
        return MarkerSpec('commands', marker_id, 'ARROW', scale=(0.4, 0.9, 0.9),
                          colour=acceleration_colour(acceleration), points=((front_x, front_y, 1.0), tip),
                          text=f'{lane_change:+d} {acceleration:+.1f}')

    def override_markers(self, marker_id: int, length: float, pose, override: ShieldOverride) -> list[MarkerSpec]:
        wanted, given = override.preferred, override.applied
        return [MarkerSpec('shield_overrides', marker_id, 'CUBE', position=(pose.x, pose.y, 0.1), yaw=pose.yaw,
                           scale=(length + 2 * OVERRIDE_MARGIN, VEHICLE_WIDTH + 2 * OVERRIDE_MARGIN, 0.2),
                           colour=OVERRIDE_COLOUR),
                MarkerSpec('shield_text', marker_id, 'TEXT_VIEW_FACING',
                           position=(pose.x, pose.y, VEHICLE_HEIGHT + 3.0), scale=(0.0, 0.0, 1.2), colour=OVERRIDE_COLOUR,
                           text=f'shield: {wanted.lane_change:+d} {wanted.acceleration:+.1f} -> '
                                f'{given.lane_change:+d} {given.acceleration:+.1f}')]

    def collision_markers(self, frame: Frame) -> list[MarkerSpec]:
        markers = []
        for _, index, x, y, vehicle_id in self.collisions:
            markers.append(MarkerSpec('collisions', index, 'CYLINDER', position=(x, y, 0.1),
                                      scale=(6.0, 6.0, 0.2), colour=rgba(COLLISION_COLOUR, 0.8)))
            markers.append(MarkerSpec('collision_text', index, 'TEXT_VIEW_FACING', position=(x, y, 4.0),
                                      scale=(0.0, 0.0, 2.5), colour=rgba(COLLISION_COLOUR),
                                      text=f'collision {vehicle_id}'))
        return markers

    def status_text(self, frame: Frame) -> MarkerSpec:
        lines = [f'episode {frame.episode}  t = {frame.time:.1f} s  mode {frame.mode or "-"}']
        highlight = False
        if frame.overrides is not None:
            highlight = self.overrides_seen is not None and frame.overrides > self.overrides_seen
            self.overrides_seen = frame.overrides
            lines.append(f'shield overrides: {frame.overrides}' + ('  (new)' if highlight else ''))
        if frame.collisions is not None:
            lines.append(f'episode ended: {frame.collisions} collision(s) (the bridge\'s count)')
        x = self.layout.road_length / 2
        y = self.layout.lane_y(self.layout.lane_count - 1) + 3 * self.layout.lane_spacing
        return MarkerSpec('status', 0, 'TEXT_VIEW_FACING', position=(x, y, 0.0), scale=(0.0, 0.0, 3.0),
                          colour=OVERRIDE_COLOUR if highlight else TEXT_COLOUR, text='\n'.join(lines))

    def observe(self, frame: Frame) -> None:
        """Take in a frame that is not drawn (a throttled or skipped one): its episode and
        its collisions still count."""
        if frame.episode != self.episode:
            self.episode, self.ids, self.collisions, self.overrides_seen = frame.episode, {}, [], None
            self.clear = True
        self.collisions = [c for c in self.collisions if frame.time - c[0] <= self.collision_hold]
        if frame.collisions == 0:
            self.collisions = []   # the bridge counted none: the vehicles that vanished were no crashes
        for vehicle in frame.crashed:
            pose = self.layout.place(vehicle)
            self.collision_count += 1
            self.collisions.append((frame.time, self.collision_count, pose.x, pose.y, vehicle.vehicle_id))

    def update(self, frame: Frame) -> list[MarkerSpec]:
        """What to send for a frame: DELETEALL on a new episode, DELETE for markers gone since
        the previous update (vehicles that left, expired collisions), then the frame's markers."""
        self.observe(frame)
        out = []
        if self.clear:
            out.append(MarkerSpec('', 0, action='DELETEALL'))
            self.shown, self.clear = set(), False
        markers = self.frame_markers(frame)
        keys = {m.key for m in markers}
        out += [MarkerSpec(ns, marker_id, action='DELETE') for ns, marker_id in sorted(self.shown - keys)]
        self.shown = keys
        return out + markers
