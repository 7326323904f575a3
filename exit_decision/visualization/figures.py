"""Files from an episode trace, with matplotlib: the time-space diagram and the bird's-eye clip.

- ``time_space_diagram``: position against time, one panel per highway lane (leftmost on
  top) and one for the exit ramps; one line per vehicle, coloured by class; every CAV lane
  change, whoever drove it (triangles pointing to the target side, in the target lane's
  panel: filled when the policy's commands drove the CAV, hollow when SUMO's driver did),
  the shield's overrides (orange circles, at the decision), collisions (red crosses; none
  where the bridge's episode end counted none) and mode switches (dashed lines, named)
  marked. The legend sits above the panels.
- ``birds_eye_clip``: the scene of ``markers.MarkerScene`` (the markers the visualizer node
  publishes) drawn from above, as an animated GIF (Pillow writer) and, where ffmpeg exists,
  an MP4; ``speed`` times real time at ``fps`` frames per second, with a progress bar.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib import animation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, FancyArrowPatch, Rectangle
from tqdm import tqdm

from exit_decision.traffic import VEHICLE_CLASSES, VehicleState
from exit_decision.visualization.layout import (
    CLASS_COLOURS,
    COLLISION_COLOUR,
    RoadLayout,
)
from exit_decision.visualization.markers import OVERRIDE_COLOUR, MarkerScene, MarkerSpec
from exit_decision.visualization.trace import EpisodeTrace

RAMPS_PANEL = 'exit ramps'
DPI = 100


@dataclass
class TimeSpace:
    """What the diagram shows, for a caller that checks or reports it."""
    path: Path
    trajectories: dict[str, str] = field(default_factory=dict)     # vehicle id -> class, of the lines drawn
    lines: list[tuple[str | int, str]] = field(default_factory=list)   # (panel, vehicle id) of each line drawn
    plot_areas: list[tuple[int, int, int, int]] = field(default_factory=list)   # panels, pixels: left, top, right, bottom
    lane_changes: int = 0                 # CAV lane changes marked
    sumo_lane_changes: int = 0            # of them, driven by SUMO's driver (released CAVs, --driver sumo)
    overrides: int = 0                    # shield overrides marked
    collisions: int = 0
    mode_switches: list[tuple[float, str, str]] = field(default_factory=list)   # time, from, to


def new_figure(size: tuple[float, float], dpi: int) -> Figure:
    """A figure with its own Agg canvas: no pyplot, no global figure state."""
    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def panel_of(vehicle: VehicleState) -> str | int:
    return vehicle.lane_index if vehicle.on_highway else RAMPS_PANEL


def time_space_diagram(trace: EpisodeTrace, layout: RoadLayout, path: Path) -> TimeSpace:
    panels: list[str | int] = [*range(layout.lane_count - 1, -1, -1), RAMPS_PANEL]
    result = TimeSpace(path)
    series: dict[str, list[tuple[float, float, str | int]]] = {}
    classes = trace.vehicle_classes()
    for frame in trace.frames:
        for vehicle in frame.vehicles:
            series.setdefault(vehicle.vehicle_id, []).append((frame.time, vehicle.position, panel_of(vehicle)))
    fig = new_figure((11, 2.0 * len(panels) + 1.2), DPI)
    axes = fig.subplots(len(panels), 1, sharex=True)
    ax_of = dict(zip(panels, axes))
    for vehicle_id, points in series.items():
        times = np.array([p[0] for p in points])
        positions = np.array([p[1] for p in points])
        where = np.array([str(p[2]) for p in points])
        colour = CLASS_COLOURS[classes[vehicle_id]]
        for panel in dict.fromkeys(p[2] for p in points):
            ax_of[panel].plot(times, np.where(where == str(panel), positions, np.nan), color=colour, lw=1.4,
                              solid_capstyle='butt', gid=vehicle_id)
            result.lines.append((panel, vehicle_id))
            result.trajectories[vehicle_id] = classes[vehicle_id]
    previous_mode, decided_at, before = '', trace.frames[0].time if trace.frames else 0.0, {}
    for frame in trace.frames:
        for vehicle in frame.vehicles:
            # a lane change as the simulation counts one (same edge, another lane), whoever drove it
            last = before.get(vehicle.vehicle_id)
            if vehicle.is_cav and last is not None and last.edge_id == vehicle.edge_id \
                    and last.lane_index != vehicle.lane_index:
                ax_of[panel_of(vehicle)].plot(frame.time, vehicle.position,
                                              '^' if vehicle.lane_index > last.lane_index else 'v', color='black',
                                              mfc='black' if last.controlled else 'white', ms=6, zorder=4)
                result.lane_changes += 1
                result.sumo_lane_changes += not last.controlled
        # overrides answer the states of the frame before (the decision step): marked there
        for vehicle_id in frame.new_overrides:
            vehicle = before.get(vehicle_id)
            if vehicle is not None:
                ax_of[panel_of(vehicle)].plot(decided_at, vehicle.position, 'o', color=OVERRIDE_COLOUR[:3], ms=6,
                                              mec='black', mew=0.4, zorder=4)
                result.overrides += 1
        for vehicle in frame.crashed if trace.collisions != 0 else ():
            ax_of[panel_of(vehicle)].plot(frame.time, vehicle.position, 'X', color=COLLISION_COLOUR, ms=10,
                                          mec='black', mew=0.5, zorder=5)
            result.collisions += 1
        if frame.mode and previous_mode and frame.mode != previous_mode:
            result.mode_switches.append((decided_at, previous_mode, frame.mode))
            for ax in axes:
                ax.axvline(decided_at, color='black', ls='--', lw=1.0, zorder=3)
            axes[0].annotate(f'{previous_mode} -> {frame.mode}', (decided_at, 1.0), xycoords=('data', 'axes fraction'),
                             xytext=(3, -12), textcoords='offset points', fontsize=8)
        previous_mode = frame.mode or previous_mode
        decided_at, before = frame.time, {v.vehicle_id: v for v in frame.vehicles}
    for panel, ax in ax_of.items():
        ax.set_ylabel('position [m]' if panel == RAMPS_PANEL else f'lane {panel} [m]')
        side = {0: ' (rightmost)', layout.lane_count - 1: ' (leftmost)'}.get(panel, '')
        ax.set_title(RAMPS_PANEL if panel == RAMPS_PANEL else f'lane {panel}{side}', fontsize=9, loc='left')
        ax.set_ylim(0, layout.road_length)
        ax.grid(alpha=0.3)
    if trace.frames:
        axes[-1].set_xlim(trace.frames[0].time, max(trace.frames[-1].time, trace.frames[0].time + trace.step_length))
    axes[-1].set_xlabel('time [s]')
    first_mode = next((f.mode for f in trace.frames if f.mode), '')
    fig.suptitle(f'{trace.label}: episode {trace.episode}' + (f', mode {first_mode}' if first_mode else ''),
                 y=0.995)
    handles = [Line2D([], [], color=CLASS_COLOURS[c], lw=2, label=c) for c in VEHICLE_CLASSES]
    handles += [Line2D([], [], ls='', marker='^', color='black', label='CAV lane change (left/right)'),
                Line2D([], [], ls='', marker='^', color='black', mfc='white', label="... by SUMO's driver"),
                Line2D([], [], ls='', marker='o', color=OVERRIDE_COLOUR[:3], mec='black', label='shield override'),
                Line2D([], [], ls='', marker='X', color=COLLISION_COLOUR, mec='black', label='collision'),
                Line2D([], [], ls='--', color='black', label='mode switch')]
    fig.legend(handles=handles, loc='upper center', ncol=math.ceil(len(handles) / 2), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.975))
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.canvas.draw()
    height = fig.get_size_inches()[1] * DPI
    for ax in axes:
        box = ax.get_window_extent()
        result.plot_areas.append((math.ceil(box.x0), math.ceil(height - box.y1), math.floor(box.x1),
                                  math.floor(height - box.y0)))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return result


class MarkerPainter:
    """Draws MarkerSpecs on a matplotlib axes seen from above (z ignored)."""
    SKIP = frozenset({'vehicle_ids', 'shield_text'})   # texts by vehicle are unreadable at a whole road's scale

    def __init__(self, ax):
        self.ax = ax
        self.artists: list = []

    def paint(self, markers: list[MarkerSpec], keep: bool = False) -> None:
        if not keep:
            for artist in self.artists:
                artist.remove()
            self.artists = []
        for marker in markers:
            if marker.action != 'ADD' or marker.namespace in self.SKIP:
                continue
            artist = self.artist(marker)
            if artist is not None and not keep:
                self.artists.append(artist)

    def artist(self, m: MarkerSpec):
        ax, colour = self.ax, m.colour[:3]
        x, y = m.position[:2]
        if m.kind == 'LINE_STRIP':
            return ax.plot([p[0] for p in m.points], [p[1] for p in m.points], color=colour, lw=0.8)[0]
        if m.kind == 'LINE_LIST':
            segments = [(m.points[i][:2], m.points[i + 1][:2]) for i in range(0, len(m.points), 2)]
            return ax.add_collection(LineCollection(segments, colors=[colour], alpha=m.colour[3], linewidths=0.4))
        if m.kind == 'CUBE':
            return ax.add_patch(Rectangle((x - m.scale[0] / 2, y - m.scale[1] / 2), m.scale[0], m.scale[1],
                                          angle=math.degrees(m.yaw), rotation_point='center', color=colour, lw=0))
        if m.kind == 'ARROW':
            (x0, y0, _), (x1, y1, _) = m.points
            return ax.add_patch(FancyArrowPatch((x0, y0), (x1, y1), arrowstyle='-|>', mutation_scale=6, lw=0.8,
                                                color=colour))
        if m.kind == 'CYLINDER':
            return ax.add_patch(Circle((x, y), m.scale[0] / 2, color=colour, alpha=m.colour[3], lw=0))
        if m.kind == 'TEXT_VIEW_FACING':
            if m.namespace == 'status':
                return ax.text(0.0, 1.02, m.text.replace('\n', '   '), transform=ax.transAxes, fontsize=9,
                               color=colour)
            return ax.text(x, y, m.text, fontsize=7, color=colour, ha='center', va='center')
        return None


def clip_stride(step_length: float, speed: float, fps: float) -> int:
    """Simulation steps per clip frame for ``speed`` times real time at ``fps``."""
    return max(1, round(speed / (fps * step_length)))


def birds_eye_clip(trace: EpisodeTrace, layout: RoadLayout, path: Path, *, speed: float = 5.0, fps: float = 10.0,
                   progress: bool = True) -> list[Path]:
    """The GIF at ``path`` (and ``path`` with .mp4 where ffmpeg exists); the files written."""
    stride = clip_stride(trace.step_length, speed, fps)
    scene = MarkerScene(layout)
    drawn = []
    for index, frame in enumerate(trace.frames):
        if index % stride == 0 or index == len(trace.frames) - 1:
            drawn.append([m for m in scene.update(frame) if m.namespace not in ('road', 'road_names')])
        else:
            scene.observe(frame)
    x0, x1, y0, y1 = layout.bounds()
    width = 14.0
    fig = new_figure((width, max(1.6, width * (y1 - y0) / (x1 - x0)) + 0.6), 80)
    ax = fig.subplots()
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect('equal')
    ax.set_xlabel('position along the road [m]', fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_yticks([])   # across the road only lanes matter; fewer labels also draw faster
    painter = MarkerPainter(ax)
    painter.paint(scene.road, keep=True)
    ax.legend(handles=[Line2D([], [], color=CLASS_COLOURS[c], lw=4, label=c) for c in VEHICLE_CLASSES],
              loc='upper left', fontsize=7, ncol=4, frameon=False)
    fig.tight_layout()
    written = []
    writers = [(path, animation.PillowWriter(fps=fps))]
    if animation.writers.is_available('ffmpeg'):
        writers.append((path.with_suffix('.mp4'), animation.FFMpegWriter(fps=fps)))
    path.parent.mkdir(parents=True, exist_ok=True)
    for target, writer in writers:   # one full draw per frame (FuncAnimation would draw each three times)
        with writer.saving(fig, target, fig.dpi):
            for markers in tqdm(drawn, desc=target.name, unit='frame', disable=not progress or len(drawn) < 50):
                painter.paint(markers)
                writer.grab_frame()
        written.append(target)
    return written


def render_episode(trace: EpisodeTrace, layout: RoadLayout, out_dir: Path, stem: str, *, speed: float = 5.0,
                   fps: float = 10.0, progress: bool = True) -> tuple[TimeSpace, list[Path]]:
    """``<stem>_time_space.png`` and ``<stem>_birds_eye.gif`` (+ .mp4) in ``out_dir``."""
    diagram = time_space_diagram(trace, layout, out_dir / f'{stem}_time_space.png')
    return diagram, birds_eye_clip(trace, layout, out_dir / f'{stem}_birds_eye.gif', speed=speed, fps=fps,
                                   progress=progress)
