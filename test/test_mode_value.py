"""A mode is one value from the decision node's parameter callback down to the network: a mode set
through the standard set_parameters service (what `ros2 param set` calls) converts its name to
weights once, and the active driver drives in that mode from the next decision."""
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rcl_interfaces.srv import SetParameters

from exit_decision.model import modes as modes_module
from exit_decision.ros.probe import ProbeNode


@pytest.fixture
def decision_node():
    """The decision node in this process (its policies loaded), spun in a thread."""
    from exit_decision.ros.nodes.decision_node import DecisionNode

    context = rclpy.context.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    node = DecisionNode(context=context)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(0.05)

    spinning = threading.Thread(target=spin, daemon=True)
    spinning.start()
    try:
        deadline = time.monotonic() + 60
        while not node.drivers and time.monotonic() < deadline:
            time.sleep(0.1)
        assert node.drivers, 'the policies loaded'
        yield node
    finally:
        stop.set()
        spinning.join(5)
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_mode_set_through_the_parameter_service_converts_its_name_to_weights_once(decision_node, monkeypatch):
    conversions = []
    convert = modes_module.weight_input
    monkeypatch.setattr(modes_module, 'weight_input', lambda mode: conversions.append(mode) or convert(mode))
    probe = ProbeNode('mode_value_probe')
    try:
        client = probe.node.create_client(SetParameters, '/decision_node/set_parameters')
        assert probe.set_parameter(client, 'mode', 'CONP', timeout=60).successful
        assert len(conversions) == 1, 'one name-to-weights conversion from the parameter to the network'
        active = decision_node.drivers[decision_node.selection.key]
        assert active.mode is decision_node.selection.mode and active.mode.name == 'CONP'
        assert list(decision_node.get_parameter('reward_weights').value) == active.mode.weights.tolist()
        point = [0.3, 0.3, 0.2, 0.2, 0.5, 0.5]   # no configured mode's
        assert probe.set_parameter(client, 'reward_weights', point, timeout=60).successful
        assert len(conversions) == 1, 'weights set alone are named, not converted from a name'
        active = decision_node.drivers[decision_node.selection.key]
        assert active.mode.name == 'custom' and np.allclose(active.mode.weights, point)
    finally:
        probe.close()
