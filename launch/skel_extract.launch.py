"""The three nodes with the packaged parameters, for full ROS 2 installs (nothing in this
package depends on it; `skel-extract replay` starts the nodes without launch).

    ros2 launch skel_extract_ros skel_extract.launch.py points:=/camera/depth/points use_sim_time:=false
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    params = os.path.join(get_package_share_directory('skel_extract_ros'), 'params', 'skel_extract.yaml')
    sim_time = {'use_sim_time': LaunchConfiguration('use_sim_time')}
    return LaunchDescription([
        DeclareLaunchArgument('points', default_value='/camera/depth/points',
                              description='the depth driver PointCloud2 topic'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        Node(package='skel_extract_ros', executable='registration_node', parameters=[params, sim_time],
             remappings=[('points', LaunchConfiguration('points'))], output='screen'),
        Node(package='skel_extract_ros', executable='accumulator_node', parameters=[params, sim_time],
             output='screen'),
        Node(package='skel_extract_ros', executable='joint_estimation_node', parameters=[params, sim_time],
             output='screen'),
    ])
