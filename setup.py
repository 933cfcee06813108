"""ament_python package definition for skel_extract_ros.

The ROS client libraries (rclpy, message packages) are not listed in install_requires:
on a ROS Jazzy install they come from /opt/ros/jazzy, and elsewhere from the wheels in
requirements-ros.txt. Listing them here would give a colcon user a second rclpy.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE_NAME = 'skel_extract_ros'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
        ('share/' + PACKAGE_NAME + '/params', glob('params/*.yaml') + glob('params/*.xml')),
        ('share/' + PACKAGE_NAME + '/launch', glob('launch/*.launch.py')),
        ('share/' + PACKAGE_NAME + '/rviz', glob('rviz/*.rviz')),
    ],
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'pykdtree>=1.3',
        'open3d>=0.18',
        'rosbags>=0.10',
        'mcap>=1.1',
        'matplotlib>=3.7',
        'PyYAML>=6.0',
        'tqdm>=4.60',
        'bvhio>=1.5',
    ],
    extras_require={
        # benchmark-only peers: Coherent Point Drift implementations and Dem Bones (SSDR)
        'bench': ['rustcpd==4.0.0', 'pycpd==2.0.0', 'py-dem-bones==0.13.1'],
    },
    zip_safe=True,
    maintainer='skel_extract_ros developers',
    maintainer_email='skel-extract@example.com',
    description='Template-free articulated skeleton extraction from single depth camera point clouds.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'skel-extract = skel_extract_ros.app.cli:main',
            'registration_node = skel_extract_ros.nodes.registration_node:main',
            'accumulator_node = skel_extract_ros.nodes.accumulator_node:main',
            'joint_estimation_node = skel_extract_ros.nodes.joint_estimation_node:main',
        ],
    },
)
