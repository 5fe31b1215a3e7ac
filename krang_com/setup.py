"""ament_python package krang_com: one ROS package, several Python packages (one per part)."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'krang_com'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    package_data={'krang_model': ['*.urdf', '*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', sorted(glob('config/*'))),
        ('share/' + package_name + '/launch', sorted(glob('launch/*.launch.py'))),
    ],
    python_requires='>=3.11',
    install_requires=[
        'setuptools',
        'ros-jazzy-rclpy[fastrtps]',
        'ros-jazzy-common-interfaces',
        'numpy',
        'numba',  # krang_model.wip_batch: the discrepancy replay's compiled batch integrator
        'scipy',
        'pin',
        'control',
        'python-can',
        'msgpack',  # python-can's udp_multicast interface (the simulated buses)
        'canopen',
        'cantools',
        'mcap',
        'mcap-ros2-support',
        'pyyaml',
        'tqdm',
        'matplotlib',
        'foxglove-sdk',  # krang view: the live Foxglove WebSocket server
        'mujoco>=4.0',  # the full-body plant (krang_sim.mujoco_plant: MjSpec, pid actuators)
    ],
    extras_require={
        'test': [
            'pytest',
            'pytest-timeout',
            'pytest-rerunfailures',
            'rosbags',
            'colcon-common-extensions',
            'ruff',
            'websockets',
        ]
    },
    zip_safe=True,
    maintainer='krang_com developers',
    maintainer_email='dev@krang-com.example',
    description='Online CoM estimation for the WIP humanoid Golem Krang (ROS 2 Jazzy).',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [
            'krang = krang_cli.main:main',
            'can_bridge = krang_ros.entry:can_bridge',
            'adrc_controller = krang_ros.entry:adrc_controller',
            'pose_server = krang_ros.entry:pose_server',
            'com_estimator = krang_ros.entry:com_estimator',
            'mcap_recorder = krang_ros.entry:mcap_recorder',
            'sim_krang = krang_ros.entry:sim_krang',
            'state_publisher = krang_ros.entry:state_publisher',
        ],
    },
)
