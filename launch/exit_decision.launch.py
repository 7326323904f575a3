"""Start the exit_decision stack on a ROS 2 Jazzy install:

    ros2 launch exit_decision exit_decision.launch.py episodes:=1

The nodes of the one table in ``exit_decision/ros/stack/node_table.py`` (the one `exit-decision
stack` starts from): a recorder writing a bag (by default a new time-stamped one under bags/,
so every run works), the graph builder and the decision node (in one process,
`graph_and_decision`; in mode AGGP unless `mode:=` says otherwise, as `exit-decision stack`),
the visualizer (markers on /exit_decision/markers; `visualizer:=false` leaves it out) and the
bridge, which waits for the others; `rviz:=true` also starts rviz2 with the shipped view of the
markers (rviz/exit_decision.rviz). The first node to exit ends the launch: the bridge when
it has run its episodes, any other node when it cannot start (its one line says why: a bad
argument, a bag path that exists) or dies, so the bridge is never left waiting for it.
`ros2 launch exit_decision exit_decision.launch.py --show-args` lists the arguments.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from exit_decision.ros.dds_defaults import apply_dds_defaults
from exit_decision.ros.stack.node_table import ARGUMENTS, BRIDGE, NODE_NAMES, OPERATOR, enclave, plan, typed

apply_dds_defaults()   # this process too (launch_ros may start a node in it), and every node it starts


def start_nodes(context):
    """The table's nodes for the arguments given, each process in its SROS2 enclave (used only
    when ROS_SECURITY_ENABLE=true: docs/ros.md, "Who may publish"); each one's exit shuts the
    launch down; and rviz2 if ``rviz`` is true."""
    given = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    return [*stack_nodes(given), *viewer(given)]


def viewer(given):
    """rviz2 with the shipped view of the markers when ``rviz`` is true; an onlooker: its exit
    ends nothing (in the operator's SROS2 enclave: it reads what the operator's tools read)."""
    if not typed('rviz', given['rviz']):
        return []
    from exit_decision.config import default_rviz_config
    return [Node(package='rviz2', executable='rviz2', arguments=['-d', str(default_rviz_config())], output='screen',
                 ros_arguments=['--enclave', enclave(OPERATOR)])]


def stack_nodes(given):
    """The table's nodes for the arguments ``given``; a composed process is not named (a name
    would rename each of its nodes)."""
    return [Node(package='exit_decision', executable=name, parameters=[parameters], output='screen',
                 name=name if NODE_NAMES[name] == (name,) else None, ros_arguments=['--enclave', enclave(name)],
                 on_exit=[Shutdown(reason=f'{BRIDGE} has run its episodes' if name == BRIDGE else
                                   f'{name} exited; the stack cannot go on without it')])
            for name, parameters in plan(given)]


def generate_launch_description():
    return LaunchDescription([
        *[DeclareLaunchArgument(name, default_value=argument.default, description=argument.description)
          for name, argument in ARGUMENTS.items()],
        OpaqueFunction(function=start_nodes),
    ])
