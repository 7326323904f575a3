"""What the stack decides, drawn: the scene as markers, time-space diagrams, bird's-eye clips.

ROS-free (no rclpy here): ``layout`` places the road and the vehicles in the plane,
``trace`` turns vehicle states, commands and modes into frames (held commands, collisions
found from vehicles that left before the end of their route), ``markers`` describes a frame
as markers (the visualizer node sends them as a ``visualization_msgs/MarkerArray``, the
clip draws the same ones), ``figures`` writes the PNG time-space diagram and the animated
bird's-eye GIF (MP4 too where ffmpeg exists) with matplotlib. Importing this package is
light: matplotlib is loaded by ``figures`` only.
"""
