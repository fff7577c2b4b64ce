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

"""Publish the simulated robot's status as diagnostic_msgs/DiagnosticStatus."""

import signal
import socket

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import (
    end_on_first_interrupt, require_positive, robot_name_or_host, robot_state_at,
    timer_period)
from roslab_demo.parameters import declare_parameters


class StatusPublisher(Node):
    """Cycle through the robot states of logic.ROBOT_STATES and report each one."""

    def __init__(self):
        super().__init__('status_publisher')
        params = declare_parameters(self, 'status_publisher')
        self.robot_name = robot_name_or_host(params['robot_name'], socket.gethostname())
        self.publishes_per_state = params['publishes_per_state']
        require_positive('publishes_per_state', self.publishes_per_state)
        self.step = 0
        self.publisher = self.create_publisher(DiagnosticStatus, params['topic'], 10)
        self.timer = self.create_timer(timer_period(params['publish_rate_hz']), self.publish)

    def publish(self):
        state = robot_state_at(self.step, self.publishes_per_state)
        msg = DiagnosticStatus()
        msg.level = bytes([state.level])  # a `byte` field: rclpy wants one-byte bytes
        msg.name = f'{self.robot_name}/status'
        msg.hardware_id = self.robot_name
        msg.message = state.message
        msg.values = [
            KeyValue(key='state', value=state.name),
            KeyValue(key='sequence', value=str(self.step)),
        ]
        self.publisher.publish(msg)
        self.step += 1


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = StatusPublisher()
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
