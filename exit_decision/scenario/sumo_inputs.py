"""SUMO input files of the scenario, generated from config: the road network and the routes.

Plain XML (nodes, edges, connections) is written from ``RoadConfig`` and compiled by
SUMO's netconvert; vehicle types and routes are written from the scenario config. Both are
cached by a hash of their text, so a scenario variant gets its own files and nothing
generated is ever edited by hand.

Edges, named by ``RoadConfig.names``: three highway sections in a row (``lane_count`` lanes,
lane 0 rightmost); the first exit leaves lane 0 at the end of the first section, the target
exit lane 0 at the end of the second.
"""
from __future__ import annotations

import hashlib
import itertools
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path
from xml.sax.saxutils import quoteattr

from exit_decision.config import RoadConfig, RoadNames, ScenarioConfig

LANE_WIDTH = 3.2   # [m] SUMO's default
SUMO_CAR_FOLLOWING = {'IDM': 'IDM', 'Krauss': 'Krauss', 'EIDM': 'EIDM'}


def _attrs(values: dict) -> str:
    return ' '.join(f'{key}={quoteattr(str(value))}' for key, value in values.items())


def sumo_tool(name: str) -> str:
    """Absolute path of a SUMO program: the installed eclipse-sumo package's own (so a user who
    calls the venv's entry point without the venv on PATH still finds it), else PATH's."""
    try:
        import sumo
        bundled = Path(sumo.SUMO_HOME) / 'bin' / name
        if bundled.is_file():
            return str(bundled)
    except ImportError:
        pass
    found = shutil.which(name)
    if found is None:
        raise RuntimeError(f'{name} not found in the eclipse-sumo package or on PATH (see README)')
    return os.path.abspath(found)   # it runs in another working directory


def diverges(names: RoadNames) -> dict[str, str]:
    """The ramp that leaves lane 0 at the end of each highway section that has one."""
    return {names.sections[0]: names.first_exit, names.sections[1]: names.target_exit}


def routes(names: RoadNames) -> dict[str, tuple[str, ...]]:
    """The edges of each route, by the edge a vehicle leaves the road by (route id ``to_<edge>``)."""
    first, second, last = names.sections
    return {last: names.sections, names.first_exit: (first, names.first_exit),
            names.target_exit: (first, second, names.target_exit)}


def network_sources(road: RoadConfig) -> dict[str, str]:
    """Plain XML node, edge and connection files for netconvert."""
    l0, l1, l2 = road.highway_lengths
    xs = [0.0, l0, l0 + l1, l0 + l1 + l2]
    # Lanes spread to the right of an edge's line (SUMO's default), 3.2 m wide. A ramp's line
    # starts where lane 0's right neighbour would be, so the ramp lane continues lane 0 and
    # crosses no other lane inside the junction; it then diverges at about 18 degrees.
    ramp_y0 = -LANE_WIDTH * (road.lane_count - 1)
    ramp_dx, ramp_dy = 0.95 * road.ramp_length, -0.31 * road.ramp_length
    nodes = [('n0', xs[0], 0.0), ('n1', xs[1], 0.0), ('n2', xs[2], 0.0), ('n3', xs[3], 0.0),
             ('exit0_end', xs[1] + ramp_dx, ramp_y0 + ramp_dy), ('exit1_end', xs[2] + ramp_dx, ramp_y0 + ramp_dy)]
    highway = dict(numLanes=road.lane_count, speed=road.highway_speed_limit, width=LANE_WIDTH)
    ramp = dict(numLanes=1, speed=road.ramp_speed_limit, length=road.ramp_length, width=LANE_WIDTH)
    sections = road.names.sections
    edges = [(section, f'n{i}', f'n{i + 1}', dict(highway, length=length))
             for i, (section, length) in enumerate(zip(sections, road.highway_lengths))]
    ramps = diverges(road.names)
    for i, (ramp_id, x) in enumerate(zip(ramps.values(), xs[1:3])):
        shape = f'{x},{ramp_y0} {x + ramp_dx},{ramp_y0 + ramp_dy}'
        edges.append((ramp_id, f'n{i + 1}', f'exit{i}_end', dict(ramp, shape=shape)))
    connections = []
    for upstream, downstream in itertools.pairwise(sections):
        connections += [(upstream, downstream, lane, lane) for lane in range(road.lane_count)]
        connections.append((upstream, ramps[upstream], 0, 0))
    return {
        'nod.xml': '<nodes>\n' + ''.join(
            f'  <node id="{n}" x="{x}" y="{y}" type="priority"/>\n' for n, x, y in nodes) + '</nodes>\n',
        'edg.xml': '<edges>\n' + ''.join(
            f'  <edge id="{e}" from="{a}" to="{b}" {_attrs(v)}/>\n' for e, a, b, v in edges) + '</edges>\n',
        'con.xml': '<connections>\n' + ''.join(
            f'  <connection from="{a}" to="{b}" fromLane="{i}" toLane="{j}"/>\n'
            for a, b, i, j in connections) + '</connections>\n',
    }


def routes_source(scenario: ScenarioConfig) -> str:
    """Vehicle types (one per class) and the three routes; vehicles are added at run time."""
    lines = ['<routes>']
    for name, vtype in scenario.vehicle_types.items():
        lines.append('  <vType ' + _attrs({
            'id': name, 'vClass': 'passenger', 'length': vtype.length, 'maxSpeed': vtype.max_speed,
            'accel': vtype.accel, 'decel': vtype.decel, 'emergencyDecel': vtype.emergency_decel,
            'speedFactor': vtype.speed_factor, 'speedDev': vtype.speed_dev,
            'lcCooperative': vtype.politeness,
            'carFollowModel': SUMO_CAR_FOLLOWING[vtype.car_following]}) + '/>')
    for leaves_by, edges in routes(scenario.road.names).items():
        lines.append(f'  <route id="to_{leaves_by}" edges="{" ".join(edges)}"/>')
    lines.append('</routes>')
    return '\n'.join(lines) + '\n'


def cache_dir() -> Path:
    return Path(os.environ.get('EXIT_DECISION_CACHE', Path(tempfile.gettempdir()) / 'exit_decision_cache'))


def _cached(kind: str, key_text: str, file_name: str, write: Callable[[Path], None]) -> Path:
    """Build ``file_name`` once per distinct input text; safe when processes race."""
    root = cache_dir()
    digest = hashlib.sha256(key_text.encode()).hexdigest()[:16]
    final = root / f'{kind}-{digest}'
    if (final / file_name).is_file():
        return final / file_name
    root.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f'tmp-{kind}-', dir=root))
    write(work)
    try:
        work.rename(final)  # atomic: nobody sees a half-written file
    except OSError:
        shutil.rmtree(work, ignore_errors=True)  # another process finished first
    return final / file_name


def build_network(road: RoadConfig) -> Path:
    """Path of the .net.xml for this road, running netconvert if it is not cached."""
    sources = network_sources(road)

    def write(work: Path) -> None:
        netconvert = sumo_tool('netconvert')
        for suffix, text in sources.items():
            (work / f'highway_exit.{suffix}').write_text(text, encoding='utf-8')
        command = [netconvert, '--node-files', 'highway_exit.nod.xml',
                   '--edge-files', 'highway_exit.edg.xml', '--connection-files', 'highway_exit.con.xml',
                   '--no-turnarounds', 'true',
                   '--junctions.limit-turn-speed', '-1',  # ramp connections keep the ramp's limit
                   '--output-file', 'highway_exit.net.xml']
        result = subprocess.run(command, cwd=work, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            raise RuntimeError(f'netconvert failed ({result.returncode}): {result.stderr.strip()}')

    return _cached('net', repr(sorted(sources.items())), 'highway_exit.net.xml', write)


def build_routes(scenario: ScenarioConfig) -> Path:
    text = routes_source(scenario)
    return _cached('routes', text, 'highway_exit.rou.xml',
                   lambda work: (work / 'highway_exit.rou.xml').write_text(text, encoding='utf-8'))
