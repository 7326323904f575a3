"""The QoS each topic is published and subscribed with, and the topic names (``topic_names.py``,
re-exported here).

QoS, on purpose, per topic (docs/design.md, "ROS 2", says the same):
- vehicle_states, traffic_graph, cav_commands: reliable (in synchronous mode every message
  of a step matters: a lost command stalls the bridge until its timeout), keep last 1000 on
  both sides in the stack's nodes (``STATES_QOS``, ``GRAPH_QOS``, ``COMMANDS_QOS``). A
  publisher's 1000 is its resend history: a reader that falls behind (a recorder sharing 2
  cores with training: with 10 it lost 30% of the states) catches up without losses. A
  node's 1000 absorbs a stall (the decision node's first policy call; a node left without
  CPU for a while on 2 busy cores, during a flood of 1000 msg/s on its topic) without losing
  the messages of its own stream among the flood. A deep queue does not make answers late
  because a node empties its stream queues at once (``take_waiting``, no executor pass per
  message) and refuses what cannot follow its episode and step from the message's header,
  before decoding it: some 10 us a refused message. Before that, rclpy's executor (0.35 ms
  a message) and its throttled logging (0.37 ms a rejected message) made a node slower than
  a flood of 1000 msg/s, and keep-last, at any depth, dropped or delayed the states and
  commands of the decision steps (56-85 command timeouts an episode). Observers (the
  launcher, the visualizer, tests) take ``STREAM_QOS``, depth 100. Messages lost anyway are
  counted (``dropped_<topic>``, from the publisher's sequence numbers, while a topic has one
  publisher: rclpy does not say which of several publishers a message came from, and its
  message_lost event does not see a reader's keep-last overflow), and the steps missing
  between two a node took as ``skipped_*``.
- the recorder subscribes with depth 1000: it must keep everything, and writing is cheap.
- episode_events: reliable, transient local, depth 50: a late subscriber (the launcher, a
  node restarted mid-episode, a recorder started later) still gets the episode that is
  running (its EVENT_STARTED starts the node's sequence checks) and the metrics of recent ones.
- /clock: best effort, keep last 1 (ROS 2's clock QoS): only the newest time matters.
- /diagnostics: reliable, keep last 10, the /diagnostics convention (one status a second).

What a queue holds: at most its depth x the largest message accepted on its topic (the size
limits of ``messages/sizes.py``, from the graph's N; the intake, ``intake.py``, refuses larger
ones once taken: the middleware cannot refuse them earlier here, so until then a queue holds
its depth of messages of any size, their memory freed once taken: config/fastdds.xml). For
N = 60: a node's states queue (graph builder, decision node alone, visualizer) 1000 x 17.9 kB =
18 MB; its graph queue 1000 x 13 kB = 13 MB; the bridge's commands queue 1000 x 9.4 kB = 9.4 MB;
the recorder's queues together about 160 MB (1000 x each of states, graph, commands, overrides,
options, parameter events; markers 100 x 0.78 MB; events 50 x 190 B). docs/ros.md, section 13,
has the table.
"""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from exit_decision.ros.topic_names import (CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC,  # noqa: F401 (re-exported)
                                           EPISODE_TOPIC, GRAPH_TOPIC, MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC,
                                           STATES_TOPIC)

STREAM_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=100)
#: what the stack's nodes publish and subscribe states, graph and commands with (see above)
STATES_QOS = GRAPH_QOS = COMMANDS_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                                                   history=HistoryPolicy.KEEP_LAST, depth=1000)
DIAGNOSTICS_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10)
RECORDER_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=1000)
EVENT_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=50,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=1)
