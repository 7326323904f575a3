"""The stack's public interface stays as users' tools and bags know it: topic names, the
reliability of the streams the synchronous loop depends on, and every message's fields and
constants (a change here breaks every recorded bag and every subscriber out there)."""
import pytest
from exit_decision_msgs import msg
from rclpy.qos import ReliabilityPolicy

from exit_decision.ros import topics

FIELDS = {
    'VehicleState': {'vehicle_id': 'string', 'vehicle_class': 'uint8', 'lane_index': 'int8', 'edge_id': 'string',
                     'position': 'double', 'lateral_offset': 'double', 'speed': 'double', 'acceleration': 'double',
                     'length': 'double', 'lane_speed_limit': 'double', 'intention': 'int8', 'route_target': 'string',
                     'controlled': 'boolean'},
    'VehicleStateArray': {'header': 'std_msgs/Header', 'episode': 'uint32', 'step': 'uint32', 'step_length': 'double',
                          'vehicles': 'sequence<exit_decision_msgs/VehicleState>'},
    'TrafficGraph': {'header': 'std_msgs/Header', 'episode': 'uint32', 'step': 'uint32', 'num_nodes': 'uint32',
                     'num_features': 'uint32', 'feature_set': 'string', 'vehicle_ids': 'sequence<string>',
                     'features': 'sequence<float>', 'adjacency': 'sequence<uint8>', 'cav_mask': 'sequence<uint8>'},
    'CavCommand': {'vehicle_id': 'string', 'lane_change': 'int8', 'acceleration': 'float'},
    'CavCommandArray': {'header': 'std_msgs/Header', 'episode': 'uint32', 'step': 'uint32', 'mode': 'string',
                        'algorithm': 'string', 'policy': 'string',
                        'commands': 'sequence<exit_decision_msgs/CavCommand>'},
    'EpisodeEvent': {'header': 'std_msgs/Header', 'episode': 'uint32', 'seed': 'int64', 'event': 'uint8',
                     'truncated': 'boolean', 'steps': 'uint32', 'v_avs': 'double', 'v_s': 'double',
                     'p_collision': 'double', 'p_collision_cav': 'double', 'n_braking': 'uint32',
                     'braking_steps': 'uint32', 'p_cav': 'double', 'p_hv2': 'double', 'reward': 'double'},
    'ShieldOverride': {'vehicle_id': 'string', 'preferred_lane_change': 'int8', 'preferred_acceleration': 'float',
                       'applied_lane_change': 'int8', 'applied_acceleration': 'float'},
    'ShieldOverrideArray': {'header': 'std_msgs/Header', 'episode': 'uint32', 'step': 'uint32',
                            'overrides': 'sequence<exit_decision_msgs/ShieldOverride>'},
    'CavOption': {'vehicle_id': 'string', 'lane_intent': 'string', 'style': 'string', 'index': 'uint16',
                  'started': 'double'},
    'CavOptionArray': {'header': 'std_msgs/Header', 'episode': 'uint32', 'step': 'uint32', 'mode': 'string',
                       'algorithm': 'string', 'policy': 'string',
                       'options': 'sequence<exit_decision_msgs/CavOption>'},
}
CONSTANTS = {
    'VehicleState': {'CLASS_HV1': 0, 'CLASS_HV2': 1, 'CLASS_HV3': 2, 'CLASS_CAV': 3,
                     'INTENTION_RIGHT': -1, 'INTENTION_KEEP': 0, 'INTENTION_LEFT': 1},
    'CavCommand': {'LANE_CHANGE_RIGHT': -1, 'LANE_CHANGE_KEEP': 0, 'LANE_CHANGE_LEFT': 1},
    'EpisodeEvent': {'EVENT_STARTED': 0, 'EVENT_ENDED': 1},
}


@pytest.mark.parametrize('name', FIELDS)
def test_every_message_keeps_its_fields_and_constants(name):
    cls = getattr(msg, name)
    assert cls.get_fields_and_field_types() == FIELDS[name]
    constants = {key: getattr(cls, key) for key in dir(cls) if key.isupper() and key != 'SLOT_TYPES'}
    assert constants == CONSTANTS.get(name, {})


def test_topic_names_stay_and_the_synchronous_loops_streams_stay_reliable():
    assert (topics.STATES_TOPIC, topics.GRAPH_TOPIC, topics.COMMANDS_TOPIC, topics.EPISODE_TOPIC,
            topics.OVERRIDES_TOPIC, topics.MARKERS_TOPIC, topics.OPTIONS_TOPIC) == (
        '/exit_decision/vehicle_states', '/exit_decision/traffic_graph', '/exit_decision/cav_commands',
        '/exit_decision/episode_events', '/exit_decision/shield_overrides', '/exit_decision/markers',
        '/exit_decision/cav_options')
    for qos in (topics.STATES_QOS, topics.GRAPH_QOS, topics.COMMANDS_QOS, topics.EVENT_QOS, topics.RECORDER_QOS):
        assert qos.reliability == ReliabilityPolicy.RELIABLE
