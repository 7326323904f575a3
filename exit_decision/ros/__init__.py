"""ROS 2 glue: message conversion and (later) the nodes. The only package that imports rclpy."""
