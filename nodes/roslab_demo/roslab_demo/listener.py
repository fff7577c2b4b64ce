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

"""Log every greeting heard on the chatter topic."""

import signal

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import end_on_first_interrupt
from roslab_demo.parameters import declare_parameters
from std_msgs.msg import String


class Listener(Node):
    """Log what the robot says on the chatter topic."""

    def __init__(self):
        super().__init__('listener')
        params = declare_parameters(self, 'listener')
        self.subscription = self.create_subscription(
            String, params['topic'], self.on_message, 10)

    def on_message(self, msg):
        self.get_logger().info(f'I heard: "{msg.data}"')


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = Listener()
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
