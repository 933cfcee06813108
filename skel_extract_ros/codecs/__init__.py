"""Messages <-> numpy: PointCloud2 (pointcloud), depth images (depth_image), rosbag2 / MCAP
files (bag), the nodes' ROS messages and JSON documents (messages), and stamps as integer
nanoseconds (stamps). The core never sees a message: the nodes, `run` and `replay` decode
and encode here."""
