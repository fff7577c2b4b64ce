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

"""Publish a numbered greeting from the robot on the chatter topic."""

import signal
import socket

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import (
    chatter_text, end_on_first_interrupt, robot_name_or_host, timer_period)
from roslab_demo.parameters import declare_parameters
from std_msgs.msg import String


class Talker(Node):
    """Say hello on the chatter topic at a steady rate."""

    def __init__(self):
        super().__init__('talker')
        params = declare_parameters(self, 'talker')
        self.robot_name = robot_name_or_host(params['robot_name'], socket.gethostname())
        self.count = 0
        self.publisher = self.create_publisher(String, params['topic'], 10)
        self.timer = self.create_timer(timer_period(params['publish_rate_hz']), self.publish)

    def publish(self):
        self.count += 1
        msg = String()
        msg.data = chatter_text(self.robot_name, self.count)
        self.publisher.publish(msg)
        self.get_logger().info(f'Publishing: "{msg.data}"')


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = Talker()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or `ros2 launch` stopping us is a normal end, not an error
    finally:
        # Ctrl-C reaches every process of a launch, and ros2 launch then sends SIGINT
        # again: a second one must not cut the clean-up short with a traceback.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
