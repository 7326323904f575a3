"""Conversion between the core's types and exit_decision_msgs, with validation.

Arrays are filled from numpy as bytes (``packed``: element-wise filling of big sequences is
slow in rclpy). ``*_from_msg`` functions raise ``MessageError`` naming the field that is
wrong, so a node can reject and count a malformed message instead of crashing.
"""
from __future__ import annotations

import array
import math
from collections.abc import Callable, Collection, Container, Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from exit_decision_msgs.msg import (CavCommand as CavCommandMsg, CavCommandArray, CavOption as CavOptionMsg,
                                    CavOptionArray, EpisodeEvent, ShieldOverride as ShieldOverrideMsg,
                                    ShieldOverrideArray, TrafficGraph as GraphMsg, VehicleState as VehicleStateMsg,
                                    VehicleStateArray)

from exit_decision.agents.options import CavOption, Option
from exit_decision.graph import TrafficGraph
from exit_decision.traffic import VEHICLE_CLASSES, CavCommand, VehicleState
from exit_decision.input_checks import InputError
from exit_decision.shield_overrides import ShieldOverride

CLASS_CODES = {name: getattr(VehicleStateMsg, f'CLASS_{name}') for name in VEHICLE_CLASSES}
CLASS_NAMES = {code: name for name, code in CLASS_CODES.items()}
#: episode metric (exit_decision.evaluation.metrics) -> EpisodeEvent field; counts are uint32
EVENT_METRICS = {'v_AVs': 'v_avs', 'v_s': 'v_s', 'p_collision': 'p_collision', 'p_collision_CAV': 'p_collision_cav',
                 'N_braking': 'n_braking', 'braking_steps': 'braking_steps', 'p_CAV': 'p_cav', 'p_HV2': 'p_hv2',
                 'reward': 'reward'}
EVENT_COUNTS = {'n_braking', 'braking_steps'}


class MessageError(InputError):
    """A message that cannot be used; the text names the field and what is wrong with it."""


def stamp_of(seconds: float) -> Time:
    whole = math.floor(seconds)
    return Time(sec=int(whole), nanosec=int(round((seconds - whole) * 1e9)) % 1_000_000_000)


def vehicle_to_msg(vehicle: VehicleState) -> VehicleStateMsg:
    return VehicleStateMsg(
        vehicle_id=vehicle.vehicle_id, vehicle_class=CLASS_CODES[vehicle.vehicle_class],
        lane_index=vehicle.lane_index, edge_id=vehicle.edge_id, position=vehicle.position,
        lateral_offset=vehicle.lateral_offset, speed=vehicle.speed, acceleration=vehicle.acceleration,
        length=vehicle.length, lane_speed_limit=vehicle.lane_speed_limit, intention=vehicle.intention,
        route_target=vehicle.route_target, controlled=vehicle.controlled)


VEHICLE_NUMBERS = ('position', 'lateral_offset', 'speed', 'acceleration', 'length', 'lane_speed_limit')


def check_vehicle_fields(vehicle_id: str, vehicle_class: int, numbers: Sequence[float]) -> None:
    """MessageError unless a vehicle's id is not empty, its class code is known and its numbers
    (``VEHICLE_NUMBERS``, in order) are finite: what a message can carry that no vehicle has.
    (``input_checks.StateLimits`` then checks the rest against the scenario.)"""
    if vehicle_class not in CLASS_NAMES:
        raise MessageError(f'vehicle {vehicle_id!r}: vehicle_class {vehicle_class} is not a known class')
    for name, value in zip(VEHICLE_NUMBERS, numbers):
        if not math.isfinite(value):
            raise MessageError(f'vehicle {vehicle_id!r}: {name} is not finite')
    if not vehicle_id:
        raise MessageError('a vehicle has an empty vehicle_id')


def check_unique_ids(vehicles: Sequence[VehicleState]) -> None:
    if len({v.vehicle_id for v in vehicles}) != len(vehicles):
        raise MessageError('vehicles: a vehicle_id appears twice')


def vehicle_from_msg(msg: VehicleStateMsg, highway_edges: Collection[str]) -> VehicleState:
    """``highway_edges``: the road's highway sections (``RoadConfig.names``); any other edge is a ramp."""
    check_vehicle_fields(msg.vehicle_id, msg.vehicle_class, [getattr(msg, name) for name in VEHICLE_NUMBERS])
    return VehicleState(
        vehicle_id=msg.vehicle_id, vehicle_class=CLASS_NAMES[msg.vehicle_class], lane_index=msg.lane_index,
        edge_id=msg.edge_id, position=msg.position, lateral_offset=msg.lateral_offset, speed=msg.speed,
        acceleration=msg.acceleration, length=msg.length, lane_speed_limit=msg.lane_speed_limit,
        intention=msg.intention, route_target=msg.route_target, controlled=msg.controlled,
        on_highway=msg.edge_id in highway_edges)


def states_to_msg(vehicles: Sequence[VehicleState], *, episode: int, step: int, step_length: float,
                  frame_id: str = 'road') -> VehicleStateArray:
    msg = VehicleStateArray(episode=episode, step=step, step_length=step_length,
                            vehicles=[vehicle_to_msg(v) for v in vehicles])
    msg.header.stamp = stamp_of(step * step_length)
    msg.header.frame_id = frame_id
    return msg


def states_from_msg(msg: VehicleStateArray, highway_edges: Collection[str]) -> list[VehicleState]:
    vehicles = [vehicle_from_msg(v, highway_edges) for v in msg.vehicles]
    check_unique_ids(vehicles)
    return vehicles


def packed(typecode: str, values: np.ndarray, dtype) -> array.array:
    """``values`` as the ``array.array`` a sequence field keeps, copied as bytes: given a numpy
    array, the generated setter converts it element by element (0.7 ms for a graph of 60)."""
    out = array.array(typecode)
    out.frombytes(np.ascontiguousarray(values, dtype=dtype).tobytes())
    return out


def graph_to_msg(graph: TrafficGraph, *, feature_set: str, episode: int, step: int,
                 stamp: Time) -> GraphMsg:
    msg = GraphMsg(episode=episode, step=step, num_nodes=graph.features.shape[0],
                   num_features=graph.features.shape[1], feature_set=feature_set,
                   vehicle_ids=list(graph.vehicle_ids))
    msg.features = packed('f', graph.features, np.float32)
    msg.adjacency = packed('B', graph.adjacency, np.uint8)
    msg.cav_mask = packed('B', graph.cav_mask, np.uint8)
    msg.header.stamp = stamp
    msg.header.frame_id = 'road'
    return msg


def graph_from_msg(msg: GraphMsg, *, expected_nodes: int | None = None,
                   expected_features: int | None = None) -> TrafficGraph:
    n, f = msg.num_nodes, msg.num_features
    if expected_nodes is not None and n != expected_nodes:
        raise MessageError(f'num_nodes is {n}, the policy expects {expected_nodes}')
    if expected_features is not None and f != expected_features:
        raise MessageError(f'num_features is {f}, the policy expects {expected_features}')
    sizes = {'features': n * f, 'adjacency': n * n, 'cav_mask': n, 'vehicle_ids': n}
    for name, size in sizes.items():
        if len(getattr(msg, name)) != size:
            raise MessageError(f'{name} has {len(getattr(msg, name))} entries, expected {size} '
                               f'for num_nodes={n}, num_features={f}')
    features = np.frombuffer(msg.features, dtype=np.float32).reshape(n, f) if n * f else np.zeros((n, f), np.float32)
    if not np.isfinite(features).all():
        raise MessageError('features contain non-finite values')
    adjacency = np.frombuffer(bytes(msg.adjacency), dtype=np.uint8).reshape(n, n)
    raw_mask = np.frombuffer(bytes(msg.cav_mask), dtype=np.uint8)
    for name, values in (('adjacency', adjacency), ('cav_mask', raw_mask)):
        if values.size and values.max() > 1:
            raise MessageError(f'{name} has entries other than 0 and 1')
    cav_mask = raw_mask.astype(bool)
    return TrafficGraph(features.copy(), adjacency.copy(), cav_mask, tuple(msg.vehicle_ids))


def commands_to_msg(commands: Mapping[str, CavCommand], *, episode: int, step: int, stamp: Time,
                    mode: str, algorithm: str, policy: str) -> CavCommandArray:
    """The message object (for who needs one: tests, bag writers); the decision node publishes
    the same message as CDR bytes (``commands_cdr.encode_commands``)."""
    msg = CavCommandArray(episode=episode, step=step, mode=mode, algorithm=algorithm, policy=policy,
                          commands=[CavCommandMsg(vehicle_id=vid, lane_change=c.lane_change,
                                                  acceleration=c.acceleration)
                                    for vid, c in commands.items()])
    msg.header.stamp = stamp
    msg.header.frame_id = 'road'
    return msg


def check_vehicle_entry(vehicle_id: str, accelerations: Iterable[float], taken: Container[str], what: str) -> None:
    """MessageError unless a per-vehicle entry names a vehicle not ``taken`` yet, with every
    acceleration finite (commands and shield overrides, from messages or CDR bytes)."""
    if vehicle_id in taken:
        raise MessageError(f'{what}: {vehicle_id!r} is listed twice')
    if not all(math.isfinite(value) for value in accelerations):
        raise MessageError(f'{what}: {vehicle_id!r} acceleration is not finite')


def _by_vehicle(entries, what: str, accelerations: Callable, decode: Callable) -> dict:
    """Entries of a per-vehicle list by vehicle id (``check_vehicle_entry``)."""
    out = {}
    for entry in entries:
        check_vehicle_entry(entry.vehicle_id, accelerations(entry), out, what)
        out[entry.vehicle_id] = decode(entry)
    return out


def commands_from_msg(msg: CavCommandArray) -> dict[str, CavCommand]:
    return _by_vehicle(msg.commands, 'commands', lambda c: (c.acceleration,),
                       lambda c: CavCommand(int(c.lane_change), float(c.acceleration)))


def overrides_to_msg(overrides: Mapping[str, ShieldOverride], *, episode: int, step: int,
                     stamp: Time) -> ShieldOverrideArray:
    msg = ShieldOverrideArray(episode=episode, step=step, overrides=[
        ShieldOverrideMsg(vehicle_id=vid, preferred_lane_change=o.preferred.lane_change,
                          preferred_acceleration=o.preferred.acceleration, applied_lane_change=o.applied.lane_change,
                          applied_acceleration=o.applied.acceleration) for vid, o in overrides.items()])
    msg.header.stamp = stamp
    msg.header.frame_id = 'road'
    return msg


def overrides_from_msg(msg: ShieldOverrideArray) -> dict[str, ShieldOverride]:
    return _by_vehicle(msg.overrides, 'shield overrides', lambda o: (o.preferred_acceleration, o.applied_acceleration),
                       lambda o: ShieldOverride(CavCommand(int(o.preferred_lane_change), float(o.preferred_acceleration)),
                                                CavCommand(int(o.applied_lane_change), float(o.applied_acceleration))))


def options_to_msg(options: Mapping[str, CavOption], *, episode: int, step: int, stamp: Time, mode: str,
                   algorithm: str, policy: str) -> CavOptionArray:
    msg = CavOptionArray(episode=episode, step=step, mode=mode, algorithm=algorithm, policy=policy, options=[
        CavOptionMsg(vehicle_id=vid, lane_intent=held.option.lane_intent, style=held.option.style, index=held.index,
                     started=held.started) for vid, held in options.items()])
    msg.header.stamp = stamp
    msg.header.frame_id = 'road'
    return msg


def options_from_msg(msg: CavOptionArray) -> dict[str, CavOption]:
    return _by_vehicle(msg.options, 'options', lambda o: (o.started,),
                       lambda o: CavOption(Option(o.lane_intent, o.style), int(o.index), float(o.started)))


def episode_event_to_msg(event: int, *, episode: int, seed: int, steps: int, time: float,
                         metrics: Mapping[str, float] | None = None, truncated: bool = False) -> EpisodeEvent:
    """An episode start (no metrics) or end (with the episode's metrics)."""
    msg = EpisodeEvent(episode=episode, seed=seed, event=event, steps=steps, truncated=truncated)
    msg.header.stamp = stamp_of(time)
    if metrics:
        for metric, name in EVENT_METRICS.items():
            setattr(msg, name, int(metrics[metric]) if name in EVENT_COUNTS else metrics[metric])
    return msg


def metrics_from_event(msg: EpisodeEvent) -> dict[str, float]:
    """The metrics of an episode-end event, keyed as the evaluation tables are."""
    return {'episode': msg.episode, 'seed': msg.seed,
            **{metric: float(getattr(msg, name)) for metric, name in EVENT_METRICS.items()},
            'steps': float(msg.steps)}
