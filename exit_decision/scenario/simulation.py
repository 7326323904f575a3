"""ROS-free wrapper around one embedded SUMO simulation of the highway-exit scenario.

``HighwaySimulation.reset(seed)`` starts an episode; ``step(commands)`` applies per-CAV
commands (lane change + acceleration), advances SUMO one step and returns the vehicle
states with what happened in the step: arrivals by exit, collisions, emergency brakings.
Same seed, same commands => same episode.

Human drivers are SUMO's (IDM + LC2013) plus two rules of ours (paper 000, Section 2.1): HV2's
opportunistic right changes, and exits chosen by the lane held at a diverge. CAVs driven
by the policy have SUMO's safety checks switched off (speed mode 0, lane-change mode 0), so
a bad command really collides; ``cav_driver='sumo'`` lets SUMO drive them to the target exit
instead (the rule-based reference). A policy CAV whose exit is decided against its task (it
committed to the first exit, or passed the target exit's diverge outside lane 0) is *released*: SUMO's own driver takes it
to the end of its route with SUMO's safety checks on, it reports ``controlled=False`` and takes
no more commands (it counts as a miss). Without this a CAV that missed the exit could stand at
the road's end until the step cap, in states no policy was trained on.
With ``single_agent`` (paper 001's SGRL training) the policy drives one CAV at a time: a CAV
that enters while another is under the policy's control is released from its start.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Literal

import numpy as np
import sumolib

from exit_decision.config import ScenarioConfig
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.scenario.sumo_inputs import build_routes
from exit_decision.traffic import (CAV, HV1, HV2, HV3, INTENTION_KEEP, INTENTION_LEFT, INTENTION_RIGHT, Arrival,
                                   CavCommand, Collision, StepResult, TrafficSnapshot, VehicleState)

Backend = Literal['libsumo', 'traci']
CavDriver = Literal['policy', 'sumo']

#: SUMO's default lane-change mode (LC2013 does everything, respects others' gaps).
SUMO_DEFAULT_LANE_CHANGE_MODE = 0b011001010101
SUMO_DEFAULT_SPEED_MODE = 31       # every safety check on
MIN_SPEED_FACTOR = 0.1             # a perturbed future's human driver still wants to move
SIGNAL_BLINKER_RIGHT, SIGNAL_BLINKER_LEFT = 1, 2


class CommandError(ValueError):
    """A CAV command that cannot be applied (unknown vehicle, not a CAV, non-finite value)."""


_SUBSCRIBED = ('VAR_LANE_ID', 'VAR_LANEPOSITION', 'VAR_LANEPOSITION_LAT', 'VAR_SPEED',
               'VAR_ACCELERATION', 'VAR_SIGNALS')

_open_libsumo: list[HighwaySimulation] = []


class HighwaySimulation:
    """One SUMO run of the scenario, restartable with ``reset`` any number of times."""

    def __init__(self, scenario: ScenarioConfig, cav_driver: CavDriver = 'policy',
                 backend: Backend = 'libsumo', single_agent: bool = False):
        self.scenario = scenario
        self.cav_driver = cav_driver
        self.single_agent = single_agent
        self.backend = backend
        if backend == 'libsumo':
            import libsumo as sumo
        else:
            import traci as sumo
        self._sumo = sumo
        self._vars = [getattr(sumo.constants, name) for name in _SUBSCRIBED]
        self.geometry = RoadGeometry.of(scenario.road)
        self._route_file = build_routes(scenario)
        self._lanes = self.geometry.lanes
        # the edge each class's route ends with: paper 000's roles (Section 2.1)
        geometry, last = self.geometry, self.geometry.sections[-1]
        self._leaves_by = {HV1: last, HV2: last, HV3: geometry.first_exit.ramp,
                           CAV: geometry.target_exit.ramp if cav_driver == 'sumo' else last}
        self._started = False

    # --- set-up -------------------------------------------------------------------------

    def _sumo_args(self, seed: int) -> list[str]:
        collision = self.scenario.collision
        return ['-n', str(self.geometry.net_file), '-r', str(self._route_file),
                '--step-length', str(self.scenario.step_length),
                '--seed', str(seed + self.scenario.sumo_seed_offset),
                '--collision.action', collision.action,
                '--collision.check-junctions', str(collision.check_junctions).lower(),
                '--collision.mingap-factor', str(collision.mingap_factor),
                '--time-to-teleport', '-1',          # a blocked road stays blocked, visibly
                '--no-step-log', 'true', '--no-warnings', 'true', '--duration-log.disable', 'true']

    def reset(self, seed: int) -> StepResult:
        """Start a new episode; returns the (empty) state at time 0."""
        args = self._sumo_args(seed)
        if not self._started:
            if self.backend == 'libsumo':
                if _open_libsumo:
                    raise RuntimeError('libsumo runs one simulation per process; close the other first')
                _open_libsumo.append(self)
            self._sumo.start([sumolib.checkBinary('sumo'), *args])
            self._started = True
        else:
            self._sumo.load(args)
        self._rng = np.random.default_rng(seed)
        self._step = 0
        self._remaining = {name: cls.count for name, cls in self.scenario.vehicle_classes.items()}
        self._serial = dict.fromkeys(self._remaining, 0)
        self._class_of: dict[str, str] = {}
        self._route_target: dict[str, str] = {}
        self._held_acceleration: dict[str, float] = {}
        self._intention: dict[str, int] = {}
        self._committed: dict[str, str] = {}   # vehicle -> highway edge whose diverge it committed to
        self._released: set[str] = set()       # policy CAVs handed to SUMO's driver after a missed exit
        self._braking: set[str] = set()
        self._inserted = 0
        self._drawn = 0
        self._last = StepResult(step=0, time=0.0, vehicles=[])
        self._snapshot = TrafficSnapshot([])
        return self._last

    def close(self) -> None:
        if self._started:
            self._sumo.close()
            self._started = False
            if self in _open_libsumo:
                _open_libsumo.remove(self)

    def __enter__(self) -> HighwaySimulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- stepping -----------------------------------------------------------------------

    @property
    def state(self) -> StepResult:
        return self._last

    @property
    def snapshot(self) -> TrafficSnapshot:
        return self._snapshot

    def validate_commands(self, commands: Mapping[str, CavCommand]) -> None:
        """Raise CommandError naming the first command that cannot be applied."""
        present = self._snapshot.by_id
        for vehicle_id, command in commands.items():
            vehicle = present.get(vehicle_id)
            if vehicle is None:
                raise CommandError(f'command for unknown vehicle {vehicle_id!r} '
                                   f'(not on the road at step {self._step})')
            if not vehicle.controlled:
                raise CommandError(f'command for {vehicle_id!r}, a {vehicle.vehicle_class} the '
                                   f'policy does not control')
            if command.lane_change not in (INTENTION_RIGHT, INTENTION_KEEP, INTENTION_LEFT):
                raise CommandError(f'{vehicle_id!r}: lane_change must be -1, 0 or 1, '
                                   f'got {command.lane_change!r}')
            if not math.isfinite(command.acceleration):
                raise CommandError(f'{vehicle_id!r}: acceleration must be finite, '
                                   f'got {command.acceleration!r}')

    def step(self, commands: Mapping[str, CavCommand] | None = None) -> StepResult:
        """Apply commands (new decisions; other CAVs hold theirs), then advance one step."""
        commands = commands or {}
        self.validate_commands(commands)
        vehicle_api = self._sumo.vehicle
        max_speed = self.scenario.vehicle_types[CAV].max_speed
        for vehicle in self._last.vehicles:
            if not vehicle.controlled:
                continue
            command = commands.get(vehicle.vehicle_id)
            if command is not None:
                self._held_acceleration[vehicle.vehicle_id] = command.acceleration
                lane_change = command.lane_change if self.geometry.lane_change_exists(
                    vehicle, command.lane_change) else 0
                self._intention[vehicle.vehicle_id] = lane_change
                if lane_change:
                    vehicle_api.changeLane(vehicle.vehicle_id, vehicle.lane_index + lane_change,
                                           self.scenario.step_length)
            speed = vehicle.speed + self._held_acceleration[vehicle.vehicle_id] * self.scenario.step_length
            vehicle_api.setSpeed(vehicle.vehicle_id, min(max(speed, 0.0), max_speed))
        self._apply_hv2_rule()
        self._route_at_diverges()
        self._insert_vehicles()
        self._sumo.simulationStep()
        self._step += 1
        self._last = self._read_step()
        return self._last

    def perturb_future(self, seed: int, speed_factor_sd: float) -> None:
        """Another future from this state, for repeated futures (``evaluation.one_step``): the rest
        of the episode's insertions drawn from a fresh stream ``seed``, and each human driver's
        desired speed factor, which the graph does not show, multiplied by 1 + N(0, sd)."""
        self._rng = np.random.default_rng(seed)
        vehicle_api = self._sumo.vehicle
        for vehicle in self._snapshot.vehicles:
            if vehicle.vehicle_class != CAV:
                factor = vehicle_api.getSpeedFactor(vehicle.vehicle_id)
                perturbed = factor * (1.0 + self._rng.normal(0.0, speed_factor_sd))
                vehicle_api.setSpeedFactor(vehicle.vehicle_id, max(perturbed, MIN_SPEED_FACTOR))

    # --- the scenario's rules -------------------------------------------------------------

    def _apply_hv2_rule(self) -> None:
        """HV2 moves one lane right whenever the right lane is clear within the clearance.

        Not in a diverge zone or on its junction (``RoadGeometry.lane_change_exists``), and a vehicle that
        has just taken a ramp still occupies lane 0 near the diverge, so ramp vehicles count as
        lane-0 traffic for the clearance.
        """
        clearance = self.scenario.vehicle_classes[HV2].right_change_clearance
        for vehicle in self._last.vehicles:
            if vehicle.vehicle_class != HV2 or not self.geometry.lane_change_exists(vehicle, -1):
                continue
            target = [self._snapshot.neighbours_of(vehicle, lane_offset=-1)]
            if vehicle.lane_index == 1:
                target += [self._snapshot.neighbours((exit_.ramp, 0), vehicle.position, vehicle.length)
                           for exit_ in self.geometry.exits.values()]
            if all(t.leader_gap >= clearance and t.follower_gap >= clearance for t in target):
                self._sumo.vehicle.changeLane(vehicle.vehicle_id, vehicle.lane_index - 1,
                                              self.scenario.step_length)

    def _route_at_diverges(self) -> None:
        """In the last metres before a diverge, the lane held picks the exit (ours; docs/design.md,
        "Scenario")."""
        commit = self.scenario.road.diverge_commit_distance
        exits, target = self.geometry.exits, self.geometry.target_exit
        for vehicle in self._last.vehicles:
            by_lane = vehicle.controlled or vehicle.vehicle_class == HV2
            if not by_lane or self._committed.get(vehicle.vehicle_id) == vehicle.edge_id:
                continue
            exit_ = exits.get(vehicle.edge_id)
            if exit_ is None or exit_.diverge_at - vehicle.position > commit:
                continue
            if vehicle.vehicle_class == HV2 and exit_ != target:
                continue
            self._committed[vehicle.vehicle_id] = vehicle.edge_id
            takes_ramp = vehicle.lane_index == 0
            if takes_ramp:
                self._sumo.vehicle.setRoute(vehicle.vehicle_id, [vehicle.edge_id, exit_.ramp])
                self._route_target[vehicle.vehicle_id] = exit_.ramp
            if vehicle.controlled and takes_ramp != (exit_ == target):
                self._release(vehicle.vehicle_id)

    def _release(self, vehicle_id: str) -> None:
        """Hand a policy CAV that missed its exit to SUMO's driver for the rest of its trip."""
        vehicle_api = self._sumo.vehicle
        vehicle_api.setSpeedMode(vehicle_id, SUMO_DEFAULT_SPEED_MODE)
        vehicle_api.setLaneChangeMode(vehicle_id, SUMO_DEFAULT_LANE_CHANGE_MODE)
        vehicle_api.setSpeed(vehicle_id, -1.0)
        self._released.add(vehicle_id)
        self._intention[vehicle_id] = INTENTION_KEEP

    def _insert_vehicles(self) -> None:
        """Per class, a Bernoulli draw per step with the paper's per-0.1 s probability."""
        lane_count = self.scenario.road.lane_count
        for name, cls in self.scenario.vehicle_classes.items():
            if self._remaining[name] == 0 or self._rng.random() >= cls.insertion_probability:
                continue
            lane = int(self._rng.integers(lane_count)) if cls.depart_lane == 'random' else cls.depart_lane
            vehicle_id = f'{name}_{self._serial[name]}'
            self._serial[name] += 1
            self._remaining[name] -= 1
            self._drawn += 1
            leaves_by = self._leaves_by[name]
            self._sumo.vehicle.add(vehicle_id, f'to_{leaves_by}', typeID=name, depart='now',
                                   departLane=str(lane), departPos='base',
                                   departSpeed=str(cls.depart_speed))
            self._class_of[vehicle_id] = name
            self._route_target[vehicle_id] = leaves_by

    # --- reading the state ----------------------------------------------------------------

    def _on_departure(self, vehicle_id: str) -> None:
        vehicle_api = self._sumo.vehicle
        vehicle_api.subscribe(vehicle_id, self._vars)
        name = self._class_of[vehicle_id]
        if name == CAV and self.cav_driver == 'policy' and self.single_agent and any(
                v.controlled for v in self._snapshot.vehicles):
            self._released.add(vehicle_id)                # SGRL: one learner at a time, SUMO drives the rest
            self._intention[vehicle_id] = INTENTION_KEEP
        elif name == CAV and self.cav_driver == 'policy':
            vehicle_api.setSpeedMode(vehicle_id, 0)       # SUMO's safety off: the policy is in control
            vehicle_api.setLaneChangeMode(vehicle_id, 0)
            self._held_acceleration[vehicle_id] = 0.0
            self._intention[vehicle_id] = INTENTION_KEEP
        elif name in (HV2, HV3):
            vehicle_api.setLaneChangeMode(vehicle_id, 0)  # HV2: only its own rule; HV3: lane 0 only

    def _read_step(self) -> StepResult:
        sim = self._sumo.simulation
        threshold = self.scenario.emergency_braking_threshold
        for vehicle_id in sim.getDepartedIDList():
            self._inserted += 1
            self._on_departure(vehicle_id)
        arrivals = []
        collisions = [Collision(c.collider, c.victim, self._class_of[c.collider], self._class_of[c.victim])
                      for c in sim.getCollisions()]
        collided = {c.collider for c in collisions} | {c.victim for c in collisions}
        for vehicle_id in sim.getArrivedIDList():
            if vehicle_id not in collided:
                exit_edge = self._previous_edge(vehicle_id)
                arrivals.append(Arrival(vehicle_id, self._class_of[vehicle_id], exit_edge,
                                        exit_edge == self.geometry.target_exit.ramp))
            self._braking.discard(vehicle_id)
        previous = self._snapshot.by_id
        results = self._sumo.vehicle.getAllSubscriptionResults()
        vehicles, braking_starts, lane_changers = [], [], []
        lane_id, lane_pos, lateral, speed, accel, signals = self._vars
        for vehicle_id, values in results.items():
            info = self._lanes[values[lane_id]]
            name = self._class_of[vehicle_id]
            before = previous.get(vehicle_id)
            changed = (before is not None and before.edge_id == info.edge_id
                       and before.lane_index != info.lane_index)
            if changed:
                lane_changers.append(vehicle_id)
            controlled = name == CAV and self.cav_driver == 'policy' and vehicle_id not in self._released
            if controlled:
                intention = self._intention[vehicle_id]
            elif changed:
                intention = INTENTION_LEFT if info.lane_index > before.lane_index else INTENTION_RIGHT
            else:
                blinkers = values[signals]
                intention = (INTENTION_RIGHT if blinkers & SIGNAL_BLINKER_RIGHT else
                             INTENTION_LEFT if blinkers & SIGNAL_BLINKER_LEFT else INTENTION_KEEP)
            acceleration = values[accel]
            if acceleration <= threshold:
                if vehicle_id not in self._braking:
                    braking_starts.append(vehicle_id)
                    self._braking.add(vehicle_id)
            else:
                self._braking.discard(vehicle_id)
            vehicles.append(VehicleState(
                vehicle_id=vehicle_id, vehicle_class=name, lane_index=info.lane_index,
                edge_id=info.edge_id, position=info.offset + values[lane_pos],
                lateral_offset=values[lateral], speed=values[speed], acceleration=acceleration,
                length=self.scenario.vehicle_types[name].length, lane_speed_limit=info.speed_limit,
                intention=intention, route_target=self._route_target[vehicle_id],
                controlled=controlled, on_highway=info.on_highway))
        self._snapshot = TrafficSnapshot(vehicles)
        total = self.scenario.total_vehicles
        return StepResult(
            step=self._step, time=self._step * self.scenario.step_length, vehicles=vehicles,
            arrivals=arrivals, collisions=collisions, braking_starts=braking_starts,
            lane_changers=lane_changers, inserted=self._inserted, waiting=self._drawn - self._inserted,
            released=frozenset(self._released),
            terminated=self._inserted == total and not vehicles and sim.getMinExpectedNumber() == 0,
            truncated=self._step >= self.scenario.max_steps)

    def _previous_edge(self, vehicle_id: str) -> str:
        before = self._snapshot.by_id.get(vehicle_id)
        return before.edge_id if before else self._route_target[vehicle_id]
