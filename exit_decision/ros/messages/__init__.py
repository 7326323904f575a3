"""Message plumbing: conversions between the core's values and the ROS messages, and the CDR codecs."""
