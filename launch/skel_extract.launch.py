"""The three nodes with a parameter file, from a camera's point clouds or depth images, in a
namespace, optionally with RViz (for full ROS 2 installs; `skel-extract replay` starts the
nodes without launch).

    ros2 launch skel_extract_ros skel_extract.launch.py input:=depth_image \\
        depth_image:=/camera/depth/image_raw camera_info:=/camera/depth/camera_info rviz:=true
    ros2 launch skel_extract_ros skel_extract.launch.py input:=cloud points:=/camera/depth/points

Arguments (ARGUMENTS below; `ros2 launch ... --show-args` lists them):
  input        cloud (PointCloud2 on `points`) or depth_image (Image on `depth_image` with
               CameraInfo on `camera_info`): the registration node's `input` parameter
  points, depth_image, camera_info   the camera driver's topics, remapped onto the node's
  params_file  the nodes' parameter file (default: the packaged params/skel_extract.yaml)
  namespace    every node and topic under it ('' = none); RViz's config uses relative
               topic names and is started in the same namespace
  rviz         true: RViz with the packaged rviz/skel_extract.rviz (subject cloud, skeleton
               markers, joint poses)
  use_sim_time true when replaying a bag with --clock
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node, PushRosNamespace

# (name, default, description, choices or None): the one list of this file's arguments
ARGUMENTS = (
    ('input', 'cloud', 'what the camera driver publishes: cloud (PointCloud2) or depth_image (Image + CameraInfo)',
     ('cloud', 'depth_image')),
    ('points', '/camera/depth/points', 'the driver\'s PointCloud2 topic (input:=cloud)', None),
    ('depth_image', '/camera/depth/image_raw', 'the driver\'s depth Image topic (input:=depth_image)', None),
    ('camera_info', '/camera/depth/camera_info', 'the driver\'s CameraInfo topic (input:=depth_image)', None),
    ('params_file', '', 'parameter file of the three nodes (empty: the packaged params/skel_extract.yaml)', None),
    ('namespace', '', 'namespace of the nodes, their topics and RViz (empty: none)', None),
    ('rviz', 'false', 'start RViz with the packaged config (subject cloud, markers, joints)', ('true', 'false')),
    ('use_sim_time', 'false', 'use /clock (a bag played with --clock)', ('true', 'false')),
)


def generate_launch_description():
    share = get_package_share_directory('skel_extract_ros')
    default_params = os.path.join(share, 'params', 'skel_extract.yaml')
    declared = [DeclareLaunchArgument(name, default_value=default, description=text,
                                      **({'choices': list(choices)} if choices else {}))
                for name, default, text, choices in ARGUMENTS]
    # an empty params_file means the packaged one (a default that is a path would show the
    # install prefix in --show-args and could not be left out on the command line)
    params_file = LaunchConfiguration('params_file')
    params = PythonExpression(["'", params_file, "' or '", default_params, "'"])
    common = [params, {'use_sim_time': LaunchConfiguration('use_sim_time')}]
    nodes = GroupAction([
        PushRosNamespace(LaunchConfiguration('namespace')),
        Node(package='skel_extract_ros', executable='registration_node',
             parameters=common + [{'input': LaunchConfiguration('input')}],
             # both remaps: the node subscribes to the one its `input` selects
             remappings=[('points', LaunchConfiguration('points')),
                         ('depth/image', LaunchConfiguration('depth_image')),
                         ('depth/camera_info', LaunchConfiguration('camera_info'))],
             output='screen'),
        Node(package='skel_extract_ros', executable='accumulator_node', parameters=common, output='screen'),
        Node(package='skel_extract_ros', executable='joint_estimation_node', parameters=common, output='screen'),
        Node(package='rviz2', executable='rviz2', name='rviz2',
             arguments=['-d', os.path.join(share, 'rviz', 'skel_extract.rviz')],
             parameters=[{'use_sim_time': LaunchConfiguration('use_sim_time')}],
             condition=IfCondition(LaunchConfiguration('rviz')), output='screen'),
    ])
    return LaunchDescription(declared + [nodes])
