"""exit_decision: graph RL highway-exit decisions for CAVs (SUMO + ROS 2)."""
