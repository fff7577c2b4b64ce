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

"""Publish a simulated temperature as sensor_msgs/Temperature."""

import signal

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import (
    end_on_first_interrupt, require_positive, simulated_temperature, timer_period)
from roslab_demo.parameters import declare_parameters
from sensor_msgs.msg import Temperature


class TemperaturePublisher(Node):
    """Stand in for a temperature sensor: a slow wave with a little noise."""

    def __init__(self):
        super().__init__('temperature_publisher')
        self.params = declare_parameters(self, 'temperature_publisher')
        require_positive('period_s', self.params['period_s'])
        self.started = self.get_clock().now()
        self.publisher = self.create_publisher(Temperature, self.params['topic'], 10)
        self.timer = self.create_timer(
            timer_period(self.params['publish_rate_hz']), self.publish)

    def publish(self):
        now = self.get_clock().now()
        msg = Temperature()
        msg.header.stamp = now.to_msg()
        msg.header.frame_id = self.params['frame_id']
        msg.temperature = simulated_temperature(
            (now - self.started).nanoseconds / 1e9,
            self.params['baseline_celsius'],
            self.params['swing_celsius'],
            self.params['period_s'],
            self.params['noise_celsius'],
        )
        msg.variance = self.params['noise_celsius'] ** 2
        self.publisher.publish(msg)


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = TemperaturePublisher()
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
