# Copyright 2026 The roslab authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
Run what a team's main host runs: the listener and the two monitors.

The main host hears its robot through ROS discovery (same ROS_DOMAIN_ID).

    ros2 launch roslab_bringup main.launch.py
    ros2 launch roslab_bringup main.launch.py params_file:=/path/to/my_params.yaml
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

# A node that ends, whether it crashed, was killed or returned, ends the whole launch: the
# roslab-nodes service (Restart=always) then starts every node again, and a node that keeps
# failing at start-up stops the service in systemd's start limit where `roslab verify` and
# `systemctl status` show it, instead of the rest running on without it.
NODE_ENDED = 'a node ended: the launch stops so that all its nodes start again together'


def generate_launch_description():
    params_file = LaunchConfiguration('params_file')
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('roslab_bringup'), 'config', 'params.yaml']),
            description='YAML file with the parameters of the demo nodes.',
        ),
        Node(package='roslab_demo', executable='listener', name='listener',
             parameters=[params_file], output='screen',
             on_exit=Shutdown(reason=NODE_ENDED)),
        Node(package='roslab_demo', executable='status_monitor', name='status_monitor',
             parameters=[params_file], output='screen',
             on_exit=Shutdown(reason=NODE_ENDED)),
        Node(package='roslab_demo', executable='temperature_monitor',
             name='temperature_monitor', parameters=[params_file], output='screen',
             on_exit=Shutdown(reason=NODE_ENDED)),
    ])
