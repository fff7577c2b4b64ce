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
Run the Pi side of the ESP32 micro-ROS demo (robot profile esp32_microros).

    ros2 launch roslab_bringup esp32.launch.py

The board's firmware (firmware/esp32_microros) publishes the potentiometer through the
micro-ROS agent (its own service, micro_ros_agent); this node answers with the servo angle.
"""

from launch import LaunchDescription
from launch.actions import Shutdown
from launch_ros.actions import Node

# As in robot.launch.py: a node that ends ends the launch, and the service starts it again.
NODE_ENDED = 'a node ended: the launch stops so that all its nodes start again together'


def generate_launch_description():
    return LaunchDescription([
        Node(package='roslab_esp32', executable='servo_follower', name='servo_follower',
             output='screen', on_exit=Shutdown(reason=NODE_ENDED)),
    ])
