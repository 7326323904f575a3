"""recorder: writes topics to a rosbag2 bag (mcap) with the rosbags library.

Subscriptions take the serialized CDR (raw) and store it unchanged, stamped with the receive
time as rosbag2 does. Ctrl-C or SIGTERM closes the bag properly: everything received is in
it and the bag is readable. Once a second the recorder closes the chunk it is filling and
flushes the file, so a recorder killed with SIGKILL loses at most about a second: its bag
has every complete chunk, and ``exit-decision bag repair`` makes it readable. By default it
records the stack's topics (``bags.DEFAULT_TOPICS``), the visualizer's markers included, so
a bag opened in Foxglove or RViz shows the scene with no extra step.

Memory stays flat however long it records: messages go to the file a chunk (1 MB, or a
second) at a time; what stays in memory per chunk is its index entry (about 100 bytes).

Parameter ``compression`` compresses each chunk (mcap's chunk compression; ``bags.open_writer``):
zstd by default, or none. Measured on one episode of the shipped scenario (60 vehicles, 800
steps = 80 s simulated, `exit-decision stack`, 2026-12-03): none 3.55 MB (about 2.7 MB per
simulated minute), zstd 0.49 MB (-86 %); the same messages rewritten with the chunks a
real-time run closes every second (71 instead of 4): zstd 0.57 MB. lz4, mcap's other chunk
compression, made 0.73 MB (0.79 MB) and is not offered. Replay, show and bag repair read zstd
and lz4 bags (test/test_bag_compression.py).

Gaps in the recorded step sequences of states (every step), graphs and commands (every
decision step) are counted per topic on /diagnostics (``gaps_<topic>``, ``missing_steps_<topic>``)
and in the summary at close: a node that died and came back leaves such a hole.

Every subscription goes through the intake (``ros/intake.py``): a message over its topic's size
limit (``messages/sizes.py``) is refused unrecorded and counted (``dropped_<topic>_too_large``
on /diagnostics, in the summary at close, and in the bag's metadata.yaml, ``custom_data``
``exit_decision.refused_too_large``), so a bag keeps the stack's traffic, not an attacker's.
A bag repaired after a SIGKILL has no such entry (it is written at close).
"""
from __future__ import annotations

import json
import time
from datetime import datetime
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosbags.rosbag2 import Writer, WriterError

from exit_decision.ros.bags.storage import (COMPRESSIONS, DEFAULT_TOPICS, KNOWN_TOPICS, message_class, open_writer,
                                            topic_qos, typestore)
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import run_node
from exit_decision.ros.intake import Intake, short
from exit_decision.errors import ParameterError
from exit_decision.ros.parameters import (check_choice, declare, declare_config, declare_cpu_affinity,
                                          describe)
from exit_decision.ros.topics import COMMANDS_TOPIC, GRAPH_TOPIC, RECORDER_QOS, STATES_TOPIC
from exit_decision.step_gaps import StepGaps

#: metadata.yaml custom_data key: the messages refused as over their topic's size limit, per
#: ``dropped_<topic>_too_large`` counter (JSON)
REFUSED_KEY = 'exit_decision.refused_too_large'
FLUSH_PERIOD = 1.0   # [s] wall clock: longest a received message stays in memory only
DEFAULT_COMPRESSION = 'zstd'


def flush(writer: Writer) -> None:
    """Close the chunk being filled and flush the file (rosbags 0.11.9's mcap writer closes a
    chunk only at 1 MB: at real time that is many seconds a SIGKILL would lose)."""
    storage = writer.storage
    if storage.chunk.bio.tell():
        storage.close_chunk()
    storage.bio.flush()


class Recorder(Node):
    def __init__(self):
        super().__init__('recorder')
        config = declare_config(self)
        declare_cpu_affinity(self)
        default_path = f'bags/exit_decision_{datetime.now():%Y%m%d_%H%M%S}'
        self.path = Path(declare(self, 'bag_path', default_path, describe(
            'directory of the bag to write', read_only=True, constraints='a directory that does not exist yet')))
        topics = list(declare(self, 'topics', list(DEFAULT_TOPICS), describe(
            'topics to record; types of others than the known ones are found on the ROS graph',
            read_only=True)))
        compression = declare(self, 'compression', DEFAULT_COMPRESSION, describe(
            'mcap chunk compression of the bag', read_only=True, constraints=' | '.join(COMPRESSIONS)))
        check_choice('compression', compression, COMPRESSIONS)
        if self.path.exists():
            raise ParameterError(f'parameter bag_path: {self.path} exists already; allowed: a directory that does '
                                 f'not exist yet (the recorder never writes into an existing bag)')
        self.store = typestore()
        try:
            self.writer = open_writer(self.path, compression)
        except (WriterError, OSError) as error:
            raise ParameterError(f'parameter bag_path: {self.path}: cannot write a bag there ({error}); '
                                 f'allowed: a directory that does not exist yet, in a writable place') from None
        self.connections = {}
        self.counts = dict.fromkeys(topics, 0)
        interval = config.env.decision_interval
        self.gaps = {topic: StepGaps(stride) for topic, stride in
                     ((STATES_TOPIC, 1), (GRAPH_TOPIC, interval), (COMMANDS_TOPIC, interval)) if topic in topics}
        self.diagnostics = Diagnostics(self, 'recorder')
        self.intake = Intake.of_config(self, self.diagnostics, config)
        self.diagnostics.figures.append(lambda: {f'recorded_{short(topic)}': count
                                                 for topic, count in self.counts.items()})
        self.waiting = [topic for topic in topics if not self.subscribe(topic, KNOWN_TOPICS.get(topic))]
        if self.waiting:
            self.discovery = self.create_timer(0.5, self.discover)
        # wall clock (steady), also under use_sim_time: a second of a 50x run is 50 s of simulation
        self.create_timer(FLUSH_PERIOD, lambda: flush(self.writer), clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'recording {", ".join(topics)} to {self.path} ({compression} compression)')

    def subscribe(self, topic: str, type_name: str | None) -> bool:
        if type_name is None:
            return False
        self.connections[topic] = self.writer.add_connection(topic, type_name, typestore=self.store)
        # over the topic's size limit: refused unrecorded and counted (the intake), so a bag
        # keeps the stack's traffic, not a flood of oversized messages
        self.intake.subscribe(message_class(type_name), topic, lambda raw, t=topic: self.write(t, raw),
                              topic_qos(topic, RECORDER_QOS), raw=True)
        return True

    def discover(self) -> None:
        found = dict(self.get_topic_names_and_types())
        for topic in list(self.waiting):
            if topic in found:
                self.subscribe(topic, found[topic][0])
                self.waiting.remove(topic)
        if not self.waiting:
            self.discovery.cancel()

    def write(self, topic: str, raw: bytes) -> None:
        self.writer.write(self.connections[topic], time.time_ns(), raw)
        self.counts[topic] += 1
        self.diagnostics.count('messages')
        gaps = self.gaps.get(topic)
        if gaps is not None:
            key = self.diagnostics.step_of(raw, f'headers_{topic.rsplit("/", 1)[-1]}')   # recorded all the same
            missing = gaps.see(*key) if key is not None else 0
            if missing:
                name = topic.rsplit('/', 1)[-1]
                self.diagnostics.count(f'gaps_{name}')
                self.diagnostics.count(f'missing_steps_{name}', missing)
                self.get_logger().warning(f'{topic}: {missing} step(s) missing before step {gaps.last} of '
                                          f'episode {gaps.episode}', throttle_duration_sec=5.0)

    def summary(self) -> str:
        counts = ', '.join(f'{topic}: {count}' for topic, count in self.counts.items())
        holes = ', '.join(f'{topic}: {g.missing} step(s) in {g.gaps} gap(s)' for topic, g in self.gaps.items()
                          if g.gaps) or 'none'
        refused = ', '.join(f'{key}: {count}' for key, count in self.refused().items()) or 'none'
        return f'{self.path} ({counts}); gaps in the step sequences: {holes}; refused as too large: {refused}'

    def refused(self) -> dict[str, int]:
        """Messages refused unrecorded, per ``dropped_<topic>_too_large`` counter."""
        return {key: int(value) for key, value in sorted(self.diagnostics.counters.items())
                if key.startswith('dropped_') and key.endswith('_too_large')}

    def destroy_node(self) -> None:
        # the bag says what it refused: metadata.yaml's custom_data (rosbag2's own field)
        self.writer.set_custom_data(REFUSED_KEY, json.dumps(self.refused()))
        self.writer.close()
        self.get_logger().info(f'bag closed: {self.summary()}')
        super().destroy_node()


def main() -> int:
    return run_node('recorder', Recorder)


if __name__ == '__main__':
    raise SystemExit(main())
