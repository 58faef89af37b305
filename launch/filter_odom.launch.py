"""Start filter_odom_node with the package's params file.

    ros2 launch gft_odom filter_odom.launch.py points_topic:=/velodyne_points use_sim_time:=false
    ros2 launch gft_odom filter_odom.launch.py params_file:=/path/to/best_mask.yaml
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

PARAMS_FILE = 'filter_odom.yaml'


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('gft_odom'), 'config', PARAMS_FILE)
    return LaunchDescription([
        DeclareLaunchArgument('points_topic', default_value='/velodyne_points',
                              description='PointCloud2 topic of the VLP-16'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='true when replaying a bag with --clock'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS params file (e.g. a band-search result)'),
        Node(
            package='gft_odom',
            executable='filter_odom_node',
            name='filter_odom_node',
            output='screen',
            parameters=[LaunchConfiguration('params_file'),
                        {'use_sim_time': LaunchConfiguration('use_sim_time')}],
            remappings=[('points', LaunchConfiguration('points_topic'))],
        ),
    ])
