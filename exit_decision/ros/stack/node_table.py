"""The stack's nodes in one table: the launch file (launch/exit_decision.launch.py) and
`exit-decision stack` (ros/stack/launcher.py) both start them from ``plan()``.

Free of rclpy and of `launch`, so the launch file, the launcher and the tests read the same
rows on any machine. Each launch argument is passed, as the parameter of the same name, to the
nodes that list it; an empty value leaves the node's own default. ``cpu_split`` is no node's
parameter: it sets each node's ``cpu_affinity``, the decision path's cores or the onlookers'
(``ros/stack/cpu_affinity.py``). The bridge comes last and waits until every other node of the plan
that listens to the vehicle states is there.

Each node's topics are here too (``ENDPOINTS``): what it publishes and subscribes to besides what
every rclpy node does. The SROS2 policy (config/sros2/policy.xml) gives each process an enclave
(``enclave``) that allows exactly these, and test/test_sros2.py holds the two together and against
the running nodes: a node added here without its permissions fails the test.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from exit_decision.config.seeds import TEST_SEED
from exit_decision.model.names import DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS
from exit_decision.ros.stack import cpu_affinity, realtime
from exit_decision.ros.topic_names import (CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC,
                                           MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC)

BRIDGE = 'sumo_bridge'


@dataclass(frozen=True)
class Argument:
    default: str
    description: str
    kind: type = str    # what the text becomes: str, int, bool (true/false) or list (of str: [a, b] or a,b)
    choices: tuple[str, ...] = ()   # the values allowed, if only some


@dataclass(frozen=True)
class StackNode:
    executable: str                 # a console_scripts entry point of setup.py
    arguments: tuple[str, ...]      # launch arguments it takes as parameters
    listens_to_states: bool         # subscribes to the vehicle states: the bridge waits for it
    enabled_by: str = ''            # a true/false argument that leaves it out when false
    composed: tuple[str, ...] = ()  # the nodes it runs in one process; empty: one, named as the executable
    decision_path: bool = False     # on the way from states to commands (else an onlooker): its cores (cpu_split)

    @property
    def node_names(self) -> tuple[str, ...]:
        return self.composed or (self.executable,)


ARGUMENTS: dict[str, Argument] = {
    # the start of `exit-decision stack` too: config/modes.yaml's aggressive punished mode (it switches to CONP)
    'mode': Argument('AGGP', "decision mode at start, a mode of config/modes.yaml; empty: the decision node's "
                             "default, the first mode of the matrix"),
    'algorithm': Argument(DEFAULT_ALGORITHM, 'a learned method of config/training.yaml with policies in policy_dir '
                                             f'(shipped, all mode-conditioned: {", ".join(SHIPPED_ALGORITHMS)}; the '
                                             'default decides over options)'),
    'modes': Argument('', "modes whose per-mode policies the decision node loads (for an algorithm without "
                          "_conditioned), a list such as [CONP]; empty: every mode of config/modes.yaml", list),
    'episodes': Argument('1', 'episodes the bridge runs, 0 = until stopped', int),
    'seed': Argument(str(TEST_SEED), 'seed of the first episode', int),
    'timing': Argument('synchronous', 'synchronous or realtime'),
    'bag_path': Argument('', 'bag directory (must not exist); empty: the recorder\'s default, '
                             'bags/exit_decision_<date>_<time>, a new one each run'),
    # the recorder's default; the values of COMPRESSIONS in ros/bags/storage.py (this table imports no rclpy)
    'compression': Argument('zstd', 'mcap chunk compression of the bag: zstd or none', choices=('zstd', 'none')),
    'visualizer': Argument('true', 'publish the scene as markers on /exit_decision/markers (true or false)', bool),
    # no node of the table takes it: the launch file starts rviz2 beside them (`exit-decision stack` never does)
    'rviz': Argument('false', 'also start rviz2 with the shipped view of the markers, share/exit_decision/rviz/'
                              'exit_decision.rviz (true or false); closing it leaves the stack running', bool),
    'use_sim_time': Argument('false', "every node takes its time from the bridge's /clock (true or false)", bool),
    'thread_priority': Argument('0', realtime.DESCRIPTION, int),
    'cpu_split': Argument('true', cpu_affinity.SPLIT_DESCRIPTION, bool),
    'config_dir': Argument('', 'directory with the YAML config; empty: the installed share/exit_decision/config'),
    'policy_dir': Argument('', 'directory with <algorithm>/policy.pt (a per-mode one: <algorithm>_<mode>/policy.pt); '
                               'empty: the shipped policies'),
}

NODES: tuple[StackNode, ...] = (
    StackNode('recorder', ('bag_path', 'compression', 'config_dir', 'use_sim_time'), listens_to_states=True),
    # the graph builder and the decision node in one process (ros/nodes/graph_and_decision.py): the
    # graph builder listens to the states and hands the decision node its graphs
    StackNode('graph_and_decision', ('config_dir', 'policy_dir', 'mode', 'modes', 'algorithm', 'use_sim_time',
                                     'thread_priority'), listens_to_states=True,
              composed=('graph_builder', 'decision_node'), decision_path=True),
    StackNode('visualizer', ('config_dir', 'use_sim_time'), listens_to_states=True, enabled_by='visualizer'),
    StackNode(BRIDGE, ('config_dir', 'episodes', 'seed', 'timing', 'use_sim_time', 'thread_priority'),
              listens_to_states=False, decision_path=True),
)


@dataclass(frozen=True)
class Endpoints:
    """What a node publishes and subscribes to, and the services of other nodes it calls, besides
    what every rclpy node does (``STANDARD_PUBLISHES``, ``STANDARD_SUBSCRIBES``, its own ``PARAMETER_SERVICES``)."""
    publishes: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    calls: tuple[str, ...] = ()


#: every rclpy node publishes its log and its parameter changes (sros2's common node profile)
STANDARD_PUBLISHES = ('/rosout', '/parameter_events')
#: ... may follow parameter events, and takes /clock under use_sim_time
STANDARD_SUBSCRIBES = ('/parameter_events', CLOCK_TOPIC)
#: the services every Jazzy rclpy node answers, under its own name (~/...)
PARAMETER_SERVICES = ('describe_parameters', 'get_parameter_types', 'get_parameters', 'get_type_description',
                      'list_parameters', 'set_parameters', 'set_parameters_atomically')

#: what the recorder records by default (bags.storage.DEFAULT_TOPICS), and so what a bag played holds
RECORDED = (STATES_TOPIC, GRAPH_TOPIC, COMMANDS_TOPIC, EPISODE_TOPIC, OVERRIDES_TOPIC, OPTIONS_TOPIC, CLOCK_TOPIC,
            '/parameter_events', MARKERS_TOPIC)
#: processes started by hand, outside ``plan()``: the bag player, and a terminal's ROS 2 tools
#: (`ros2 param`, `ros2 topic echo`; their node's name is their own, ``OPERATOR`` stands for it)
PLAYER, OPERATOR = 'player', 'operator'

#: node -> its topics, for every node of NODES and the processes started by hand (docs/nodes.md's table)
ENDPOINTS: dict[str, Endpoints] = {
    'recorder': Endpoints(publishes=(DIAGNOSTICS_TOPIC,), subscribes=RECORDED),
    'graph_builder': Endpoints(publishes=(GRAPH_TOPIC, DIAGNOSTICS_TOPIC), subscribes=(EPISODE_TOPIC, STATES_TOPIC)),
    # composed: the graph builder hands it the episode's start, the checked states and the graph in the process
    'decision_node': Endpoints(publishes=(COMMANDS_TOPIC, OVERRIDES_TOPIC, OPTIONS_TOPIC, DIAGNOSTICS_TOPIC)),
    'visualizer': Endpoints(publishes=(MARKERS_TOPIC, DIAGNOSTICS_TOPIC),
                            subscribes=(EPISODE_TOPIC, STATES_TOPIC, COMMANDS_TOPIC, GRAPH_TOPIC, OVERRIDES_TOPIC,
                                        OPTIONS_TOPIC, DIAGNOSTICS_TOPIC)),
    BRIDGE: Endpoints(publishes=(CLOCK_TOPIC, STATES_TOPIC, EPISODE_TOPIC, DIAGNOSTICS_TOPIC),
                      subscribes=(COMMANDS_TOPIC,)),
    # a bag's topics, as recorded, and the episode starts it makes for a bag without them
    PLAYER: Endpoints(publishes=RECORDED),
    # reads every topic of the stack, publishes none; sets and gets the nodes' parameters
    OPERATOR: Endpoints(subscribes=(*RECORDED, DIAGNOSTICS_TOPIC),
                        calls=tuple(f'/{node}/{service}' for node in ('recorder', 'graph_builder', 'decision_node',
                                                                      'visualizer', BRIDGE, PLAYER)
                                    for service in PARAMETER_SERVICES)),
}


def enclave(process: str) -> str:
    """The SROS2 enclave a process of the stack (an executable, or PLAYER, OPERATOR) runs in: one
    per process, for every node it holds (config/sros2/policy.xml)."""
    return f'/exit_decision/{process}'


#: enclave -> the nodes it holds: the plan's processes, the player and the operator's tools
ENCLAVES: dict[str, tuple[str, ...]] = {**{enclave(node.executable): node.node_names for node in NODES},
                                        enclave(PLAYER): (PLAYER,), enclave(OPERATOR): (OPERATOR,)}


_BOOLEANS = {'true': True, 'false': False, '1': True, '0': False}


def typed(name: str, text: str):
    """The value of argument ``name`` given as ``text``; ValueError naming it and what is allowed."""
    kind, choices = ARGUMENTS[name].kind, ARGUMENTS[name].choices
    if choices and text not in choices:
        raise ValueError(f'argument {name}: {text!r} is not allowed; allowed: {" | ".join(choices)}')
    if kind is list:
        return [item.strip().strip('\'"') for item in text.strip().strip('[]').split(',') if item.strip()]
    try:
        return _BOOLEANS[text.lower()] if kind is bool else kind(text)
    except (KeyError, ValueError):
        allowed = 'true or false' if kind is bool else 'an integer' if kind is int else 'a string'
        raise ValueError(f'argument {name}: {text!r} is not allowed; allowed: {allowed}') from None


#: executable -> the ROS nodes its process runs
NODE_NAMES: dict[str, tuple[str, ...]] = {node.executable: node.node_names for node in NODES}


def process_of(node_name: str, executables) -> str:
    """Which of these executables (of the table) runs the node ``node_name``."""
    return next(executable for executable in executables if node_name in NODE_NAMES[executable])


def _texts(given: Mapping[str, object]) -> dict[str, str]:
    """Every argument's text: the given ones (text, or Python values), the defaults for the rest."""
    unknown = sorted(set(given) - set(ARGUMENTS))
    if unknown:
        raise ValueError(f'unknown argument(s) {", ".join(unknown)}; known: {", ".join(ARGUMENTS)}')
    text = {name: argument.default for name, argument in ARGUMENTS.items()}
    text.update({name: str(value).lower() if isinstance(value, bool) else ','.join(value) if isinstance(value, list)
                 else str(value) for name, value in given.items()})
    return text


def cores(given: Mapping[str, object]) -> tuple[list[int], list[int]] | None:
    """(the decision path's cores, the onlookers' cores) for these argument values, from the
    cores this process may use; None when the nodes are not split (``cpu_split`` false, 1 core,
    or a real-time ``thread_priority``: on its share of the cores the synchronous path would
    keep them busy, and the kernel's reservation for their normal tasks would stop it for tens
    of ms; ``ros/stack/cpu_affinity.py``). The launcher's and the benchmark's own helper nodes are
    onlookers too."""
    return _split(_texts(given))


def _split(text: Mapping[str, str]) -> tuple[list[int], list[int]] | None:
    if not typed('cpu_split', text['cpu_split']) or typed('thread_priority', text['thread_priority']):
        return None
    return cpu_affinity.split(cpu_affinity.usable())


def plan(given: Mapping[str, object], extra_listeners: int = 0) -> list[tuple[str, dict[str, object]]]:
    """(executable, parameters) of each node to start, in order, the bridge last, for these
    argument values (text as `ros2 launch` gives it, or Python values; missing: the default).
    ``extra_listeners``: state subscribers outside the table the bridge waits for too (the
    launcher's own helper node)."""
    text = _texts(given)
    nodes = [node for node in NODES if not node.enabled_by or typed(node.enabled_by, text[node.enabled_by])]
    listeners = sum(node.listens_to_states for node in nodes) + extra_listeners
    split = _split(text)
    started = []
    for node in nodes:
        parameters = {name: typed(name, text[name]) for name in node.arguments if text[name] != ''}
        parameters = {name: value for name, value in parameters.items() if value != []}   # [] has no ROS type
        if split:
            parameters['cpu_affinity'] = split[0] if node.decision_path else split[1]
        if node.executable == BRIDGE:
            parameters['wait_for_subscribers'] = listeners
        started.append((node.executable, parameters))
    return started
