"""Messages <-> numpy: PointCloud2 (pointcloud), depth images (depth_image), rosbag2 / MCAP
files (bag), and the nodes' ROS messages and JSON documents (messages). The core never
sees a message: the nodes, `run` and `replay` decode and encode here."""
