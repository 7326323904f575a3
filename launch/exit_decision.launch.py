"""Start the exit_decision stack on a ROS 2 Jazzy install:

    ros2 launch exit_decision exit_decision.launch.py mode:=AGGI episodes:=1

The bridge, graph builder and decision node, a recorder writing a bag, and the visualizer
(markers on /exit_decision/markers for RViz/Foxglove; `visualizer:=false` leaves it out). On
machines without `launch`, `exit-decision stack` does the same (and switches the mode mid-run).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    arguments = {
        'mode': ('AGGI', 'decision mode at start'),
        'algorithm': ('mdgqn_conditioned', 'mdgqn_conditioned (one network, every mode), gqn or mdgqn'),
        'episodes': ('1', 'episodes the bridge runs, 0 = until stopped'),
        'seed': ('10000', 'seed of the first episode'),
        'timing': ('synchronous', 'synchronous or realtime'),
        'bag_path': ('bags/exit_decision', 'bag directory (must not exist)'),
        'visualizer': ('true', 'publish the scene as markers on /exit_decision/markers (true or false)'),
    }
    config = {name: LaunchConfiguration(name) for name in arguments}
    return LaunchDescription([
        *[DeclareLaunchArgument(name, default_value=default, description=text)
          for name, (default, text) in arguments.items()],
        Node(package='exit_decision', executable='recorder', name='recorder',
             parameters=[{'bag_path': config['bag_path']}]),
        Node(package='exit_decision', executable='graph_builder', name='graph_builder'),
        Node(package='exit_decision', executable='decision_node', name='decision_node',
             parameters=[{'mode': config['mode'], 'algorithm': config['algorithm']}]),
        Node(package='exit_decision', executable='visualizer', name='visualizer',
             condition=IfCondition(config['visualizer'])),
        Node(package='exit_decision', executable='sumo_bridge', name='sumo_bridge',
             parameters=[{'episodes': config['episodes'], 'seed': config['seed'], 'timing': config['timing']}]),
    ])
