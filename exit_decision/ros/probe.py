"""A helper node inside a non-ROS program (the launcher, a benchmark, a test), with its own context."""
from __future__ import annotations

import time
from collections.abc import Callable

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from exit_decision.ros.executor import Waiter   # first: it sets the DDS defaults before rclpy starts


class ProbeNode:
    """A node inside a non-ROS program (the launcher, a benchmark, a test) with its own
    context and executor, so it never touches the global rclpy context."""

    def __init__(self, name: str):
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.waiter = Waiter([self.node], self.executor)

    def spin_once(self, timeout_sec: float) -> None:
        """Take what is waiting, or wait up to ``timeout_sec`` for something (``Waiter``)."""
        self.waiter.spin_once(timeout_sec)

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            self.spin_once(0.05)
        return condition()

    def call(self, client, request, timeout: float, attempt: float = 10.0):
        """Call a service through ``client``; its response, or None when no answer came within
        ``timeout`` seconds. A request unanswered after ``attempt`` seconds is sent again (the
        calls made here, getting and setting parameters, are harmless to repeat): right after
        discovery the server's response can be lost before the client's response reader is
        matched (Fast DDS: "failed to send response (timeout)", seen on fresh clones)."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            future = client.call_async(request)
            self.executor.spin_until_future_complete(future, timeout_sec=min(attempt, left))
            if future.done() and future.result():
                return future.result()
            client.remove_pending_request(future)
        return None

    def set_parameter(self, client, name: str, value, timeout: float, attempt: float = 10.0):
        """Call a node's set_parameters service (what `ros2 param set` calls) through ``client``
        (``call``); the SetParametersResult, or None when no answer came within ``timeout`` seconds."""
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        response = self.call(client, request, timeout, attempt)
        return response.results[0] if response is not None else None

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
