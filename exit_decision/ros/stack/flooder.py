"""One flooding process of ``bench flood`` (``stack/flood.py``): pre-serialized messages on one
topic at a set rate, for a set time, then one JSON line on stdout (sent, bytes, refused, start, end).

Kinds of message (``payloads``), all serialized once before the flood:
- ``stale``: well-formed, of the topic's type, from the past: episode 0, step 5 (a decision
  step the stack left long ago) where the type has them; the type's default message elsewhere;
- ``oversized``: over the topic's size limit. Most are the stale message with one more
  alignment's worth of bytes than the limit allows (cheap to send, so the rate is the flood's);
  every ``huge_every``-th is a huge one: the graph with a 3601 x 3601 adjacency (and 3601 x F
  features), the states of 60,000 vehicles, any other topic's stale message padded to
  3601 x 3601 bytes.

The publisher offers the topic's QoS (its durability and reliability, so the stack's readers
match it) with a history of 100: a reader behind by more loses the oldest before they reach it (so
what the flooders sent is at most what reached a node), and the flood's memory stays small.
"""
from __future__ import annotations

import argparse
import array
import json
import time

HUGE_SIDE = 3601            # N x N + 1 for the shipped N = 60: an adjacency 3601 x 3601
HUGE_VEHICLES = 60_000
STALE_EPISODE, STALE_STEP = 0, 5


def stale_message(topic: str, num_nodes: int, feature_set: str) -> bytes:
    """A well-formed message of ``topic``'s type, of episode 0, step 5 (where it has them)."""
    from rclpy.serialization import serialize_message

    from exit_decision.graph import FEATURE_SETS
    from exit_decision.ros.bags.storage import KNOWN_TOPICS, message_class
    from exit_decision.ros.messages.states_cdr import encode_states
    from exit_decision.ros.topics import GRAPH_TOPIC, STATES_TOPIC

    if topic == STATES_TOPIC:
        return encode_states([], episode=STALE_EPISODE, step=STALE_STEP, step_length=0.1)
    msg = message_class(KNOWN_TOPICS[topic])()
    if hasattr(msg, 'episode'):   # an EpisodeEvent: episode 0's start announced again
        msg.episode = STALE_EPISODE
    if hasattr(msg, 'step'):
        msg.step = STALE_STEP
    if topic == GRAPH_TOPIC:
        features = len(FEATURE_SETS[feature_set])
        fill_graph(msg, num_nodes, features, feature_set)
    return serialize_message(msg)


def fill_graph(msg, nodes: int, features: int, feature_set: str) -> None:
    msg.num_nodes, msg.num_features, msg.feature_set = nodes, features, feature_set
    msg.vehicle_ids = [''] * nodes
    msg.features = array.array('f', bytes(4 * nodes * features))
    msg.adjacency = array.array('B', bytes(nodes * nodes))
    msg.cav_mask = array.array('B', bytes(nodes))


def huge_message(topic: str, stale: bytes, feature_set: str) -> bytes:
    """The huge oversized message of ``topic`` (module docstring)."""
    from exit_decision_msgs.msg import TrafficGraph
    from rclpy.serialization import serialize_message

    from exit_decision.graph import FEATURE_SETS
    from exit_decision.ros.messages.states_cdr import encode_states
    from exit_decision.ros.topics import GRAPH_TOPIC, STATES_TOPIC
    from exit_decision.traffic import VehicleState

    if topic == STATES_TOPIC:
        vehicle = VehicleState('HV1_0', 'HV1', 0, 'Highway_0', 10.0, 0.0, 20.0, 0.0, 5.0, 25.0, 0, 'Highway_2',
                               False, True)
        return encode_states([vehicle] * HUGE_VEHICLES, episode=STALE_EPISODE, step=STALE_STEP, step_length=0.1)
    if topic == GRAPH_TOPIC:
        msg = TrafficGraph(episode=STALE_EPISODE, step=STALE_STEP)
        fill_graph(msg, HUGE_SIDE, len(FEATURE_SETS[feature_set]), feature_set)
        return serialize_message(msg)
    return padded(stale, HUGE_SIDE * HUGE_SIDE)


def padded(message: bytes, size: int) -> bytes:
    """``message`` with zero bytes after it up to ``size`` bytes, a multiple of 4."""
    size += -size % 4
    return message + bytes(max(size - len(message), 0))


def payloads(topic: str, kind: str, limit: int, num_nodes: int, feature_set: str, huge_every: int) -> list[bytes]:
    """The messages the flooder sends, in turn."""
    stale = stale_message(topic, num_nodes, feature_set)
    if kind == 'stale':
        return [stale]
    over = padded(stale, limit + 8)
    return [over] * (huge_every - 1) + [huge_message(topic, stale, feature_set)] if huge_every else [over]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('topic')
    parser.add_argument('kind', choices=('stale', 'oversized'))
    parser.add_argument('--rate', type=float, required=True, help='[msg/s]')
    parser.add_argument('--seconds', type=float, required=True)
    parser.add_argument('--limit', type=int, required=True, help='[bytes] the topic\'s size limit')
    parser.add_argument('--num-nodes', type=int, required=True)
    parser.add_argument('--feature-set', required=True)
    parser.add_argument('--huge-every', type=int, default=100, help='every n-th oversized message is huge; 0: none')
    parser.add_argument('--subscribers', type=int, default=1, help='wait (up to 10 s) until this many match')
    parser.add_argument('--start-at', type=float, default=0.0, help='[s, wall clock] start then (the flooders together)')
    args = parser.parse_args(argv)

    from exit_decision.ros.probe import ProbeNode   # first: the DDS defaults
    from rclpy.duration import Duration
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.qos import QoSProfile

    from exit_decision.ros.bags.storage import KNOWN_TOPICS, message_class, topic_qos
    from exit_decision.ros.topics import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, RECORDER_QOS

    messages = payloads(args.topic, args.kind, args.limit, args.num_nodes, args.feature_set, args.huge_every)
    offered = DIAGNOSTICS_QOS if args.topic == DIAGNOSTICS_TOPIC else topic_qos(args.topic, RECORDER_QOS)
    qos = QoSProfile(history=offered.history, depth=100, reliability=offered.reliability,
                     durability=offered.durability)
    probe = ProbeNode('flooder')
    publisher = probe.node.create_publisher(message_class(KNOWN_TOPICS[args.topic]), args.topic, qos)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() < args.subscribers and time.monotonic() < deadline:
        probe.spin_once(0.05)
    time.sleep(max(args.start_at - time.time(), 0.0))
    sent = size = refused = 0
    start = time.time()
    began = time.monotonic()
    end = began + args.seconds
    while (now := time.monotonic()) < end:
        due = int((now - began) * args.rate) + 1 - sent
        if due <= 0:
            time.sleep(min(0.001, end - now))
            continue
        for _ in range(due):
            message = messages[(sent + refused) % len(messages)]
            try:
                publisher.publish(message)
            except _rclpy.RCLError:   # the sender's middleware refuses it (a best-effort sample too large to send)
                refused += 1
                continue
            sent += 1
            size += len(message)
    elapsed = time.monotonic() - began
    # what is still in the history reaches the readers before the writer goes (reliable topics)
    publisher.wait_for_all_acked(Duration(seconds=5.0))
    print(json.dumps({'sent': sent, 'bytes': size, 'refused': refused, 'start': start, 'end': start + elapsed}),
          flush=True)
    probe.close()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
