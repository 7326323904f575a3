"""The largest serialized message each topic of the stack can carry, from the graph's node count
N (config/graph.yaml ``max_vehicles``) and the messages' CDR layout: what the nodes' intake
(``ros/intake.py``) accepts, checked on the raw bytes before anything is decoded.

Free of rclpy: plain arithmetic over the layout of ``msg_defs/msg`` (``cdr`` says how plain
CDR lays a message out). Each bound is an upper bound: every string at ``NAME_BYTES`` (a policy
path at ``PATH_BYTES``), every alignment at its widest padding, every array at its most entries:
N vehicles a step (the scenario never has more on the road than the graph has rows:
``input_checks.StateLimits.max_vehicles``), N commands, overrides or options a decision, an N x N
adjacency. What is within the bound is then checked field by field (``input_checks``); what is
over it is refused unread, however it came.

Topics the layout does not bound by N (``/diagnostics``, ``/parameter_events``: counters and
parameters, a few kB) get ``TEXT_TOPIC_BYTES``; a topic the recorder is asked to record that the
stack does not know gets ``DEFAULT_LIMIT``.
"""
from __future__ import annotations

from exit_decision.graph import FEATURE_SETS
from exit_decision.ros.topic_names import (CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC,
                                           MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC)

#: [bytes] longest name a message of the stack carries: vehicle, edge, route, mode, algorithm,
#: feature set, lane intent, style, frame id (the scenario's are under 20)
NAME_BYTES = 64
#: [bytes] longest policy file path (Linux's PATH_MAX)
PATH_BYTES = 4096
#: [bytes] /diagnostics and /parameter_events: a node's counters, a parameter change (1-2 kB)
TEXT_TOPIC_BYTES = 16 * 1024
#: [bytes] a topic outside the stack's (the recorder's ``topics`` parameter may name one)
DEFAULT_LIMIT = 1024 * 1024
#: [bytes] one visualization_msgs/Marker without its points: header, pose, scale, colour, the
#: empty texture and mesh fields, and a text of up to 600 bytes (the status text)
MARKER_BYTES = 1024
#: the road's line strips and names, drawn once (the shipped road: 11 markers, 16 points)
ROAD_MARKERS, ROAD_POINTS = 64, 1024
#: markers the visualizer draws per vehicle at most: body, id, command arrow, two shield, two collision
MARKERS_PER_VEHICLE = 8
POINT_BYTES = 24    # geometry_msgs/Point: 3 float64

ENCAPSULATION = 4
PAD8 = 7            # the most padding one alignment adds


def string(size: int = NAME_BYTES) -> int:
    """A CDR string of up to ``size`` bytes: uint32 length, bytes, NUL, padding to 4 before it."""
    return 3 + 4 + size + 1


def header() -> int:
    """std_msgs/Header after the encapsulation: stamp (2 x 4), frame_id."""
    return 8 + string()


def stamped(*, entries: int, entry: int, names: int = 0, paths: int = 0) -> int:
    """A message of the stack's stamped shape: encapsulation, header, uint32 episode and step,
    ``names`` strings and ``paths`` paths, then an array of ``entries`` entries of ``entry``
    bytes (each aligned: PAD8)."""
    return (ENCAPSULATION + header() + 8 + names * string() + paths * string(PATH_BYTES)
            + PAD8 + 4 + entries * (entry + PAD8))


def size_limits(num_nodes: int, feature_set: str) -> dict[str, int]:
    """Topic -> the most bytes a serialized message on it may have, for a graph of ``num_nodes``
    rows (N) and the feature layout ``feature_set``."""
    n, features = num_nodes, len(FEATURE_SETS[feature_set])
    vehicle = 3 * string() + 2 + 6 * 8 + 1 + 1 + 3 * PAD8   # id, class, lane, edge, 6 float64, intention, route, controlled
    graph = (ENCAPSULATION + header() + 8 + 8 + string() + 4 + n * string()
             + 3 * (PAD8 + 4) + 4 * n * features + n * n + n)
    markers = ROAD_MARKERS * MARKER_BYTES + ROAD_POINTS * POINT_BYTES + 4 + n * MARKERS_PER_VEHICLE * (MARKER_BYTES + 2 * POINT_BYTES) \
        + MARKER_BYTES + n * n * 2 * POINT_BYTES   # the graph's edges: one line list, 2 points an edge
    return {
        STATES_TOPIC: ENCAPSULATION + header() + 8 + PAD8 + 8 + 4 + n * (vehicle + PAD8),
        GRAPH_TOPIC: graph,
        COMMANDS_TOPIC: stamped(entries=n, entry=string() + 1 + 4, names=2, paths=1),
        OVERRIDES_TOPIC: stamped(entries=n, entry=string() + 2 * (1 + 3 + 4)),
        OPTIONS_TOPIC: stamped(entries=n, entry=3 * string() + 2 + 8, names=2, paths=1),
        EPISODE_TOPIC: ENCAPSULATION + header() + 4 + 8 + 4 + 4 + 5 * 8 + 2 * 4 + 3 * 8 + 2 * PAD8,
        CLOCK_TOPIC: ENCAPSULATION + 8,
        DIAGNOSTICS_TOPIC: TEXT_TOPIC_BYTES,
        '/parameter_events': TEXT_TOPIC_BYTES,
        MARKERS_TOPIC: markers,
    }


def limits_of(config) -> dict[str, int]:
    """``size_limits`` of a project config (its graph's N and feature set)."""
    return size_limits(config.graph.max_vehicles, config.graph.feature_set)
