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
Follow the ESP32 board's potentiometer with its servo (seed 000's circuit).

Subscribes /esp32/potentiometer (std_msgs/Int32, the raw 12-bit reading the board's firmware
publishes) and publishes /esp32/servo_angle (std_msgs/Int32, 0-180), which the firmware
writes to the servo. The last angle is published again every second, so `roslab verify` and
`ros2 topic echo` see it while nobody turns the knob.
"""

import signal

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_esp32.logic import POTENTIOMETER_TOPIC, servo_angle, SERVO_ANGLE_TOPIC
from std_msgs.msg import Int32


class ServoFollower(Node):
    """Turn each potentiometer reading into a servo angle for the board."""

    def __init__(self):
        super().__init__('servo_follower')
        self.angle = None
        self.publisher = self.create_publisher(Int32, SERVO_ANGLE_TOPIC, 10)
        self.subscription = self.create_subscription(
            Int32, POTENTIOMETER_TOPIC, self.on_reading, 10)
        self.timer = self.create_timer(1.0, self.republish)

    def on_reading(self, msg):
        angle = servo_angle(msg.data)
        if angle != self.angle:
            self.get_logger().info(f'potentiometer {msg.data} -> servo {angle} degrees')
        self.angle = angle
        self.publish()

    def republish(self):
        if self.angle is not None:
            self.publish()

    def publish(self):
        self.publisher.publish(Int32(data=self.angle))


def main(args=None):
    rclpy.init(args=args)
    node = ServoFollower()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or `ros2 launch` stopping us is a normal end, not an error
    finally:
        # ros2 launch sends SIGINT again after Ctrl-C: no traceback in the clean-up.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
