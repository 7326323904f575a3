"""Node parameters: declared with a descriptor, refused with a reason that names them, followed when set."""
from __future__ import annotations

from pathlib import Path

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from exit_decision.config import ProjectConfig, default_config_dir, load_project
from exit_decision.errors import ParameterError, PolicyError
from exit_decision.model.modes import CUSTOM_MODE, ModeWeights
from exit_decision.model.names import DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS, default_policy_dir, planned_policies
from exit_decision.model.selection import PolicySelection
from exit_decision.ros.stack import cpu_affinity, realtime


def describe(description: str, *, read_only: bool = False, integer_range: tuple[int, int] | None = None,
             float_range: tuple[float, float] | None = None, constraints: str = '') -> ParameterDescriptor:
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=constraints)
    if integer_range is not None:
        descriptor.type = ParameterType.PARAMETER_INTEGER
        descriptor.integer_range = [IntegerRange(from_value=integer_range[0], to_value=integer_range[1], step=1)]
    if float_range is not None:
        descriptor.type = ParameterType.PARAMETER_DOUBLE
        descriptor.floating_point_range = [FloatingPointRange(from_value=float_range[0], to_value=float_range[1])]
    return descriptor


def allowed_values(descriptor: ParameterDescriptor, default) -> str:
    """What a parameter's descriptor allows, in words."""
    if descriptor.additional_constraints:
        return descriptor.additional_constraints
    if descriptor.integer_range:
        r = descriptor.integer_range[0]
        return f'an integer in {r.from_value}..{r.to_value}'
    if descriptor.floating_point_range:
        r = descriptor.floating_point_range[0]
        return f'a number in [{r.from_value:g}, {r.to_value:g}]'
    kind = {bool: 'true or false', str: 'a string', int: 'an integer', float: 'a number'}
    if isinstance(default, list):
        return f'a list of {kind.get(type(default[0]), "values") if default else "values"}'
    return kind.get(type(default), 'a value of its type')


def declare(node: Node, name: str, default, descriptor: ParameterDescriptor):
    """``node.declare_parameter(...).value``; a value given at start that the type or range
    refuses raises ParameterError naming the parameter and what is allowed."""
    try:
        return node.declare_parameter(name, default, descriptor).value
    except ParameterException:
        given = getattr(node, '_parameter_overrides', {}).get(name)
        shown = repr(given.value) if given is not None else 'the value given'
        raise ParameterError(f'parameter {name}: {shown} is not allowed; allowed: '
                             f'{allowed_values(descriptor, default)}') from None


def follow(node: Node, *names: str) -> None:
    """Apply new values of these parameters at once: ``node.<name>`` takes every accepted value
    (the descriptor's type and range have checked it). Parameters a node reads only at start
    are declared ``read_only`` instead, so a new value is refused rather than ignored."""
    def apply(parameters: list[Parameter]) -> None:
        for parameter in parameters:
            if parameter.name in names:
                setattr(node, parameter.name, parameter.value)
    node.add_post_set_parameters_callback(apply)


def check_choice(name: str, value, choices) -> None:
    """Raise ParameterError unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ParameterError(f'parameter {name}: {value!r} is not allowed; allowed: {" | ".join(choices)}')


def declare_thread_priority(node: Node) -> int:
    """Declare the read-only ``thread_priority`` of a node on the decision path (bridge, graph
    builder, decision node) and apply it to every thread of the process: its own, the
    middleware's, and those it starts later (they inherit it). 0, the default, leaves the
    OS's normal scheduling. 1-99 runs them with real-time SCHED_FIFO at that priority, as
    ros2_control's controller manager runs its loop: on a machine whose cores the onlookers
    (recorder, visualizer) share, a wake-up on the decision path then never waits behind
    another process (docs/design.md, "ROS 2 -> Speed"). Needs the right to: CAP_SYS_NICE, or an
    rtprio limit of at least that priority; without it the node does not start, and says so."""
    priority = declare(node, 'thread_priority', 0, describe(
        realtime.DESCRIPTION, read_only=True, integer_range=(realtime.PRIORITIES[0], realtime.PRIORITIES[-1])))
    if priority:
        try:
            realtime.apply(priority)
        except realtime.RealtimeRefused as refused:
            raise ParameterError(f'parameter thread_priority: {refused}') from None
    return priority


def declare_cpu_affinity(node: Node) -> list[int]:
    """Declare the read-only ``cpu_affinity`` of a node (default: every core the process may use
    at start, so ``ros2 param get`` tells where it runs) and pin every thread of the process to
    those cores: its own, the middleware's, and those it starts later. The stack gives the
    decision path and the onlookers cores of their own (``cpu_split``; ``ros/stack/cpu_affinity.py``
    says why)."""
    cores = declare(node, 'cpu_affinity', cpu_affinity.AT_START, describe(
        cpu_affinity.DESCRIPTION, read_only=True,
        constraints=f'a non-empty list of the cores this process may use, {cpu_affinity.AT_START}'))
    cores = list(cores or [])   # `-p cpu_affinity:=[]` comes as None (no type)
    reason = cpu_affinity.refusal(cores)
    if reason:
        raise ParameterError(f'parameter cpu_affinity: {reason}')
    if sorted(set(cores)) != cpu_affinity.usable():
        cpu_affinity.pin(cores)
    return cores


def declare_config(node: Node) -> ProjectConfig:
    """Declare the read-only ``config_dir`` parameter and load the project config from it."""
    value = declare(node, 'config_dir', '', describe(
        'directory with the YAML config; empty: the installed share/exit_decision/config',
        read_only=True))
    return load_project(Path(value) if value else default_config_dir())


def start_algorithm(algorithms: list[str]) -> str:
    """The decision node's algorithm when none is given: the shipped policy (``DEFAULT_ALGORITHM``,
    the launch file's and ``exit-decision stack``'s too) when it is loaded, else the last loaded."""
    return DEFAULT_ALGORITHM if DEFAULT_ALGORITHM in algorithms else algorithms[-1]


def declare_policy_selection(node: Node, config: ProjectConfig) -> tuple[Path, PolicySelection]:
    """The decision node's policy parameters (policy_dir, modes, algorithm, algorithms, mode,
    reward_weights): the policy directory and the selection of the start values (PolicyError, in
    one line, for values no policy can drive with)."""
    policy_dir = Path(declare(node, 'policy_dir', '', describe(
        'directory with <algorithm>[_<mode>]/policy.pt; empty: the shipped policies', read_only=True))
        or default_policy_dir())
    modes = list(declare(node, 'modes', config.mode_matrix.modes, describe(
        'modes whose per-mode policies are loaded at start', read_only=True))) or [None]
    algorithm = declare(node, 'algorithm', '', describe(
        'a learned method of config/training.yaml, _options after it for one over options, _conditioned at '
        f'the end for one policy of every mode; one of parameter algorithms; empty at start: the shipped policy '
        f'({DEFAULT_ALGORITHM}) when it is loaded, else the last of them',
        constraints='an algorithm of parameter algorithms'))
    shipped = not algorithm or algorithm in SHIPPED_ALGORITHMS
    algorithms = list(declare(node, 'algorithms', list(SHIPPED_ALGORITHMS) if shipped else [algorithm], describe(
        f'algorithms whose policies are loaded at start; default: the shipped ones ({", ".join(SHIPPED_ALGORITHMS)}), '
        'or only the start algorithm if it is another', read_only=True))) or [None]
    if None in (algorithms[0], modes[0]):
        raise PolicyError('parameters algorithms and modes: give at least one of each')
    mode = declare(node, 'mode', modes[0], describe('decision mode', constraints=' | '.join([*config.modes, CUSTOM_MODE])))
    start = ModeWeights(config).mode(mode if mode in config.modes else modes[0]).weights
    weights = declare(node, 'reward_weights', start.tolist(), describe(
        'the mode\'s weights: result, efficiency, comfort, safety (sum 1), incentive, punishment '
        '(sum 1); a conditioned policy decides for any such point; given at start, they name the mode'))
    selection = PolicySelection(config, planned_policies(algorithms, modes), algorithm or start_algorithm(algorithms),
                                mode, weights)
    for name, value in (('algorithm', selection.algorithm), ('mode', selection.mode.name)):   # the start values
        if value != node.get_parameter(name).value:                                         # the selection settled on
            node.set_parameters([Parameter(name, Parameter.Type.STRING, value)])
    return policy_dir, selection
