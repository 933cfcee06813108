"""ROS 2 nodes: thin adapters around skel_extract_ros.core."""
