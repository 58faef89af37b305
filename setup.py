from glob import glob

from setuptools import find_packages, setup

package_name = 'gft_odom'

setup(
    name=package_name,
    version='1.0.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    python_requires='>=3.10',
    # Pure-Python/numerical dependencies. ROS 2 itself (rclpy, message packages) comes from the
    # ROS install (apt) on a robot, or from requirements-ros.txt (pip wheels) in the dev venv.
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'open3d-cpu>=0.18; platform_machine == "x86_64"',
        'open3d>=0.18; platform_machine != "x86_64"',
        'rosbags>=0.10',
        'pyyaml',
        'tqdm',
        'matplotlib',
    ],
    extras_require={
        # kiss-icp: the peer the benchmarks measure against; evalio: six more LiDAR-only peers
        # (gft_odom.bench.peers); genz-icp: GenZ-ICP with its own deskew (gft_odom.bench.genz);
        # ray: band search on a cluster.
        'test': ['pytest', 'hypothesis', 'evo', 'ruff', 'kiss-icp>=1.3.0', 'evalio==0.6.1',
                 'genz-icp==0.3.2', 'ray>=2.9'],
        'peers': ['evalio==0.6.1', 'genz-icp==0.3.2'],
        'ray': ['ray>=2.9'],
    },
    zip_safe=True,
    maintainer='gft_odom developers',
    maintainer_email='gft-odom@example.org',
    description='Graph-frequency filtered LiDAR odometry for orchards (ROS 2 Jazzy).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'filter_odom_node = gft_odom.ros.node:main',
            'gft-odom = gft_odom.tools.cli:main',
        ],
    },
)
