"""The stack's topic names, free of rclpy: the node table (``stack/node_table.py``) declares
from them what each node publishes and subscribes to; ``topics.py`` adds the QoS and re-exports them."""

STATES_TOPIC = '/exit_decision/vehicle_states'
GRAPH_TOPIC = '/exit_decision/traffic_graph'
COMMANDS_TOPIC = '/exit_decision/cav_commands'
EPISODE_TOPIC = '/exit_decision/episode_events'
CLOCK_TOPIC = '/clock'
DIAGNOSTICS_TOPIC = '/diagnostics'
MARKERS_TOPIC = '/exit_decision/markers'
OVERRIDES_TOPIC = '/exit_decision/shield_overrides'
#: the option each policy CAV holds, per decision step (a policy over options only)
OPTIONS_TOPIC = '/exit_decision/cav_options'
