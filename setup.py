from glob import glob

from setuptools import find_packages, setup

package_name = 'solid_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        # ROS layout: ros2 launch finds share/<pkg>/launch; the sources stay under config/.
        ('share/' + package_name + '/launch', glob('config/launch/*.launch.yaml')),
        ('share/' + package_name + '/rviz', glob('config/rviz/*.rviz')),
    ],
    python_requires='>=3.10',
    install_requires=['setuptools', 'numpy', 'scipy', 'pyyaml', 'rosbags', 'mcap', 'matplotlib',
                      'small-gicp', 'gtsam>=4.3'],
    extras_require={
        'test': ['pytest', 'pytest-xdist', 'ruff', 'mypy', 'types-PyYAML'],
        # ROS 2 Jazzy client libraries from PyPI, for machines without a ROS install.
        'ros-pypi': ['ros-jazzy-rclpy', 'ros-jazzy-common-interfaces',
                     'ros-jazzy-rmw-fastrtps-cpp', 'colcon-common-extensions'],
        # KISS-ICP odometry for clouds without odometry (odometry_source: kiss_icp).
        'kiss': ['kiss-icp'],
    },
    zip_safe=True,
    maintainer='solid_ros maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-7b7549ff.example',
    description='SOLiD LiDAR loop closure: verified loops with a 6-DoF pose for LiDAR SLAM.',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [
            'solid_node = solid_ros.ros.node:main',
            'solid_replay = solid_ros.tools.replay:main',
            'solid_demo = solid_ros.tools.demo:main',
        ],
    },
)
