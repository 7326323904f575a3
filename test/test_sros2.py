"""Who may publish: the SROS2 policy and governance (config/sros2/) against the node table.

The policy gives every process of the table an enclave, ``node_table.enclave``, and each of its
nodes a profile that allows exactly the table's ``ENDPOINTS`` plus what every rclpy node uses; the
player and the operator's tools get one each. Read with xml.etree, names resolved as sros2's
permissions template resolves them (``/x`` as is, ``~/x`` under the node, ``x`` under the
namespace). A node added to the table fails here until the policy holds its permissions, and one
that makes a topic the table does not list fails the test that runs the nodes. The pip wheels'
Fast DDS has no security plugins, so no test enforces the permissions (docs/ros.md).
"""
from __future__ import annotations

import subprocess
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from exit_decision.ros.stack.node_table import (BRIDGE, ENCLAVES, ENDPOINTS, NODES, OPERATOR, PARAMETER_SERVICES,
                                                PLAYER, RECORDED, STANDARD_PUBLISHES, STANDARD_SUBSCRIBES, Endpoints,
                                                enclave, plan)
from exit_decision.ros.topic_names import (CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC,
                                           MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC)

REPO = Path(__file__).resolve().parent.parent
POLICY = REPO / 'config' / 'sros2' / 'policy.xml'
GOVERNANCE = REPO / 'config' / 'sros2' / 'governance.xml'


@dataclass
class Allowed:
    """What a profile allows, fully qualified names."""
    publish: set[str] = field(default_factory=set)
    subscribe: set[str] = field(default_factory=set)
    reply: set[str] = field(default_factory=set)
    request: set[str] = field(default_factory=set)


def qualified(name: str, ns: str, node: str) -> str:
    """A policy name as sros2's permissions template makes it fully qualified."""
    ns = ns if ns.endswith('/') else ns + '/'
    return name if name.startswith('/') else ns + node + name[1:] if name.startswith('~') else ns + name


def read_policy(path: Path) -> dict[str, dict[str, Allowed]]:
    """enclave -> node -> what its profile allows. Only literal names and ALLOW rules: a
    wildcard, a DENY or an action would allow or deny more than the table says."""
    root = ET.parse(path).getroot()
    assert (root.tag, root.get('version')) == ('policy', '0.2.0'), 'an sros2 policy, format 0.2.0'
    policy: dict[str, dict[str, Allowed]] = {}
    for enclave_element in root.findall('enclaves/enclave'):
        nodes = policy.setdefault(enclave_element.get('path'), {})
        for profile in enclave_element.findall('profiles/profile'):
            ns, node = profile.get('ns'), profile.get('node')
            allowed = nodes.setdefault(node, Allowed())
            for rules in profile:
                assert rules.tag in ('topics', 'services'), f'{node}: <{rules.tag}> (the stack has no actions)'
                for kind, value in rules.attrib.items():
                    assert value == 'ALLOW', f'{node}: {kind}="{value}" (only ALLOW rules: the default denies)'
                    for item in rules:
                        assert not set(item.text) & set('*?[]{}'), f'{node}: {item.text} is not a literal name'
                        getattr(allowed, kind).add(qualified(item.text, ns, node))
    return policy


def expected(node: str) -> Allowed:
    """What the table and the standard set give a node."""
    own = ENDPOINTS[node]
    return Allowed(publish={*STANDARD_PUBLISHES, *own.publishes}, subscribe={*STANDARD_SUBSCRIBES, *own.subscribes},
                   reply={f'/{node}/{service}' for service in PARAMETER_SERVICES}, request=set(own.calls))


def mismatches(policy: dict[str, dict[str, Allowed]], enclaves: dict[str, tuple[str, ...]]) -> list[str]:
    """Every way the policy and the table differ, one line each (empty: they agree)."""
    found = [f'{path}: no enclave in the policy' for path in enclaves if path not in policy]
    found += [f'{path}: an enclave the table has no process for' for path in policy if path not in enclaves]
    for path, nodes in enclaves.items():
        if path not in policy:
            continue
        profiles = policy[path]
        found += [f'{path}: no profile for node {node}' for node in nodes if node not in profiles]
        found += [f'{path}: profile {node} is no node of the process' for node in profiles if node not in nodes]
        for node in set(nodes) & set(profiles):
            want, have = expected(node), profiles[node]
            for kind in ('publish', 'subscribe', 'reply', 'request'):
                missing, extra = getattr(want, kind) - getattr(have, kind), getattr(have, kind) - getattr(want, kind)
                found += [f'{path} {node}: {kind} {name} not allowed' for name in sorted(missing)]
                found += [f'{path} {node}: {kind} {name} allowed, not in the table' for name in sorted(extra)]
    return found


def test_every_process_of_the_table_has_an_enclave_allowing_exactly_its_nodes_topics():
    assert set(ENDPOINTS) == {name for names in ENCLAVES.values() for name in names}, 'every node has its topics'
    assert {enclave(node.executable) for node in NODES} | {enclave(PLAYER), enclave(OPERATOR)} == set(ENCLAVES)
    assert ENCLAVES[enclave('graph_and_decision')] == ('graph_builder', 'decision_node'), 'one enclave, two nodes'
    assert mismatches(read_policy(POLICY), ENCLAVES) == []


def test_only_the_bridge_and_the_player_publish_states_and_only_the_decision_node_and_the_player_commands():
    """Issue 40's rule, read from the policy itself: who may write each of the stack's topics."""
    writers: dict[str, set[str]] = {}
    for nodes in read_policy(POLICY).values():
        for node, allowed in nodes.items():
            for topic in allowed.publish:
                writers.setdefault(topic, set()).add(node)
    for topics, allowed in (((STATES_TOPIC, EPISODE_TOPIC, CLOCK_TOPIC), {BRIDGE, PLAYER}),
                            ((COMMANDS_TOPIC, OVERRIDES_TOPIC, OPTIONS_TOPIC), {'decision_node', PLAYER}),
                            ((GRAPH_TOPIC,), {'graph_builder', PLAYER}), ((MARKERS_TOPIC,), {'visualizer', PLAYER})):
        for topic in topics:
            assert writers[topic] == allowed, (topic, writers[topic])
    assert not writers.keys() - {*RECORDED, *STANDARD_PUBLISHES, DIAGNOSTICS_TOPIC}
    assert all(OPERATOR not in nodes for topic, nodes in writers.items() if topic not in STANDARD_PUBLISHES)
    # and every topic a node may read, some node of the stack may write
    readers = {topic for nodes in read_policy(POLICY).values() for allowed in nodes.values()
               for topic in allowed.subscribe}
    assert readers <= writers.keys(), readers - writers.keys()


def test_the_checks_find_a_node_added_without_its_permissions_and_each_kind_of_mistake():
    policy = read_policy(POLICY)
    assert mismatches(policy, {**ENCLAVES, '/exit_decision/planner': ('planner',)}) == [
        '/exit_decision/planner: no enclave in the policy']
    composed = {**ENCLAVES, enclave('graph_and_decision'): ('graph_builder', 'decision_node', 'planner')}
    assert mismatches(policy, composed) == ['/exit_decision/graph_and_decision: no profile for node planner']
    bridge = policy[enclave(BRIDGE)][BRIDGE]
    bridge.publish.add(COMMANDS_TOPIC)
    bridge.subscribe.discard(COMMANDS_TOPIC)
    assert mismatches(policy, ENCLAVES) == [
        f'/exit_decision/sumo_bridge sumo_bridge: publish {COMMANDS_TOPIC} allowed, not in the table',
        f'/exit_decision/sumo_bridge sumo_bridge: subscribe {COMMANDS_TOPIC} not allowed']
    assert qualified('~/get_parameters', '/', 'recorder') == '/recorder/get_parameters'
    assert qualified('rosout', '/ns', 'recorder') == '/ns/rosout'


@pytest.mark.parametrize('text, problem', [
    ('<topics publish="ALLOW"><topic>/exit_decision/*</topic></topics>', 'not a literal name'),
    ('<topics publish="DENY"><topic>/x</topic></topics>', 'only ALLOW rules'),
    ('<actions call="ALLOW"><action>/x</action></actions>', 'no actions')])
def test_a_wildcard_a_deny_or_an_action_in_the_policy_is_refused(tmp_path, text, problem):
    path = tmp_path / 'policy.xml'
    path.write_text(f'<policy version="0.2.0"><enclaves><enclave path="/a"><profiles><profile ns="/" node="a">'
                    f'{text}</profile></profiles></enclave></enclaves></policy>')
    with pytest.raises(AssertionError, match=problem):
        read_policy(path)


def test_the_recorder_and_the_player_have_the_recorders_default_topics():
    from exit_decision.ros.bags.storage import DEFAULT_TOPICS
    assert set(RECORDED) == set(DEFAULT_TOPICS)


def test_the_launch_file_starts_each_process_in_its_enclave(monkeypatch):
    from test_launch import launch_description
    _, actions = launch_description(monkeypatch, {})
    started = {a.kwargs['executable']: a.kwargs['ros_arguments'] for a in actions if type(a).__name__ == 'Node'}
    assert started == {name: ['--enclave', enclave(name)] for name, _ in plan({})}
    assert {enclave(name) for name in started} <= read_policy(POLICY).keys()


def test_the_governance_admits_only_authenticated_participants_and_checks_every_topic():
    root = ET.parse(GOVERNANCE).getroot()
    (rule,) = root.findall('domain_access_rules/domain_rule')
    ranges = [(int(r.findtext('min')), int(r.findtext('max'))) for r in rule.findall('domains/id_range')]
    assert ranges == [(0, 232)], 'every ROS domain id: the project gives tests and parallel runs their own'
    assert rule.findtext('allow_unauthenticated_participants') == 'false'
    assert rule.findtext('enable_join_access_control') == 'true'
    assert rule.findtext('rtps_protection_kind') in ('SIGN', 'ENCRYPT')
    (topics,) = rule.findall('topic_access_rules/topic_rule')
    assert topics.findtext('topic_expression') == '*'
    assert topics.findtext('enable_write_access_control') == topics.findtext('enable_read_access_control') == 'true'


# --- the table's topics are the nodes' own ------------------------------------------------------

def empty_bag(path: Path) -> Path:
    """A bag with the recorder's default connections and no message (what the player publishes)."""
    from exit_decision.ros.bags.storage import DEFAULT_TOPICS, open_writer, typestore
    writer, store = open_writer(path), typestore()
    for topic, type_name in DEFAULT_TOPICS.items():
        writer.add_connection(topic, type_name, typestore=store)
    writer.close()
    return path


def graph_of(node, name: str) -> Endpoints | None:
    """What node ``name`` has on the ROS graph, as the table writes it (its parameter services
    and the standard topics left out; what else it answers goes to ``calls``, to be seen); None
    before it is seen."""
    if name not in node.get_node_names():
        return None
    publishes = {topic for topic, _ in node.get_publisher_names_and_types_by_node(name, '/')}
    subscribes = {topic for topic, _ in node.get_subscriber_names_and_types_by_node(name, '/')}
    services = {service for service, _ in node.get_service_names_and_types_by_node(name, '/')}
    clients = {service for service, _ in node.get_client_names_and_types_by_node(name, '/')}
    answers = services - {f'/{name}/{service}' for service in PARAMETER_SERVICES}
    return Endpoints(tuple(sorted(publishes - set(STANDARD_PUBLISHES))), tuple(sorted(subscribes)),
                     tuple(sorted(clients | {f'answers {service}' for service in answers})))


def table_of(name: str) -> Endpoints:
    own = ENDPOINTS[name]
    return Endpoints(tuple(sorted(set(own.publishes) - set(STANDARD_PUBLISHES))), tuple(sorted(set(own.subscribes))),
                     tuple(sorted(own.calls)))


def test_the_running_nodes_publish_and_subscribe_what_the_table_says(tmp_path):
    """The table's processes (the bridge held before its first step), then the player (holding a
    bag with the recorder's topics for 30 s before it plays), each as its own process: every
    node's publishers, subscriptions and services on the ROS graph are the table's, so a topic a
    node makes and the table (and so the policy) lacks fails here."""
    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.stack.launcher import start_node
    from ros_helpers import random_policies, small_config_dir, stop
    config_dir = small_config_dir(tmp_path / 'config')
    given = {'config_dir': str(config_dir), 'policy_dir': str(random_policies(config_dir, tmp_path / 'policies')),
             'bag_path': str(tmp_path / 'bag'), 'cpu_split': False}
    table = [(name, {**parameters, **({'wait_for_subscribers': 99} if name == BRIDGE else {})})
             for name, parameters in plan(given)]
    player = [(PLAYER, {'bag_path': str(empty_bag(tmp_path / 'played')), 'wait_for_subscribers': 99})]
    processes: dict[str, subprocess.Popen] = {}
    test = ProbeNode('sros2_test')
    try:
        for started in (table, player):
            for name, parameters in started:
                processes[name] = start_node(name, parameters, tmp_path / f'{name}.log')
            names = [node for process, _ in started for node in ENCLAVES[enclave(process)]]
            deadline, seen = time.monotonic() + 120, {}
            while time.monotonic() < deadline:
                seen = {name: graph_of(test.node, name) for name in names}
                if all(seen[name] == table_of(name) for name in names):
                    break
                dead = {name: (tmp_path / f'{name}.log').read_text()[-500:] for name, process in processes.items()
                        if process.poll() is not None}
                assert not dead, dead
                test.spin_once(0.5)
            assert seen == {name: table_of(name) for name in names}
    finally:
        test.close()
        for process in processes.values():
            stop(process)
