"""The skeleton extraction algorithm: pure numpy / scipy / Open3D, never rclpy."""
