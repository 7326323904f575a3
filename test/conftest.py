"""Shared fixtures. Every test process keeps DDS on loopback in its own domain."""
import os

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))

import pytest  # noqa: E402

from exit_decision.config import default_config_dir, load_project  # noqa: E402
from exit_decision.traffic import VehicleState  # noqa: E402


@pytest.fixture(scope='session')
def project_config():
    return load_project()


@pytest.fixture(scope='session')
def per_mode_policies(tmp_path_factory):
    """A policy directory of the shipped config with untrained per-mode policies (gqn, mdgqn at
    every mode) beside conditioned ones: none ships, and per-mode switching stays tested."""
    from ros_helpers import random_policies
    return random_policies(default_config_dir(), tmp_path_factory.mktemp('per_mode_policies'))


def make_vehicle(vehicle_id: str, vehicle_class: str = 'HV1', *, lane: int = 0, position: float = 0.0,
                 speed: float = 20.0, acceleration: float = 0.0, edge: str = 'Highway_0',
                 intention: int = 0, limit: float = 25.0) -> VehicleState:
    """A hand-made vehicle state (length 5 m)."""
    return VehicleState(vehicle_id=vehicle_id, vehicle_class=vehicle_class, lane_index=lane, edge_id=edge,
                        position=position, lateral_offset=0.0, speed=speed, acceleration=acceleration,
                        length=5.0, lane_speed_limit=limit, intention=intention,
                        route_target='Highway_2', controlled=vehicle_class == 'CAV',
                        on_highway=edge.startswith('Highway'))
