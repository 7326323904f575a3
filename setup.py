"""ament_python package exit_decision: executables land in lib/exit_decision (for `ros2 run`)."""
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = 'exit_decision'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    # the intake's take loop in C (exit_decision/ros/_drain.c): Python.h only, no ROS headers
    ext_modules=[Extension('exit_decision.ros._drain', ['exit_decision/ros/_drain.c'])],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + PACKAGE + '/config/sros2', glob('config/sros2/*.xml')),   # docs/ros.md, "Who may publish"
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
        ('share/' + PACKAGE + '/rviz', glob('rviz/*.rviz')),   # the launch file's rviz:=true
    ] + [('share/' + PACKAGE + '/' + directory, [directory + '/policy.pt'])
         for directory in sorted(glob('policies/*')) if glob(directory + '/policy.pt')],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='exit_decision developers',
    maintainer_email='exit-decision@users.noreply.github.com',
    description='Graph RL highway-exit decision stack for CAVs (SUMO + ROS 2 Jazzy).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'exit-decision = exit_decision.cli:main',
            'sumo_bridge = exit_decision.ros.nodes.sumo_bridge:main',
            'graph_builder = exit_decision.ros.nodes.graph_builder:main',
            'decision_node = exit_decision.ros.nodes.decision_node:main',
            'graph_and_decision = exit_decision.ros.nodes.graph_and_decision:main',
            'recorder = exit_decision.ros.nodes.recorder:main',
            'player = exit_decision.ros.nodes.player:main',
            'visualizer = exit_decision.ros.nodes.visualizer:main',
        ],
    },
)
