"""ROS 2 glue, the only package that imports rclpy: nodes/, messages/, bags/, stack/ and the nodes' shared helpers."""
