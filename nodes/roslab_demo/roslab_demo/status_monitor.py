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

"""Log each robot status at its own severity, and notice a silent robot."""

import signal

from diagnostic_msgs.msg import DiagnosticStatus
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import (
    end_on_first_interrupt, level_code, log_at_level, SilenceWatch, status_line)
from roslab_demo.parameters import declare_parameters


class StatusMonitor(Node):
    """Turn robot status messages into info, warning and error log lines."""

    def __init__(self):
        super().__init__('status_monitor')
        params = declare_parameters(self, 'status_monitor')
        self.silence = SilenceWatch(params['silent_after_s'], self.seconds_now())
        self.subscription = self.create_subscription(
            DiagnosticStatus, params['topic'], self.on_status, 10)
        self.silence_timer = self.create_timer(1.0, self.check_silence)

    def seconds_now(self):
        return self.get_clock().now().nanoseconds / 1e9

    def on_status(self, msg):
        back = self.silence.heard(self.seconds_now())
        if back:
            self.get_logger().info(back)
        values = {pair.key: pair.value for pair in msg.values}
        level = level_code(msg.level)
        line = status_line(msg.hardware_id, level, values.get('state', '?'), msg.message)
        log_at_level(self.get_logger(), level, line)

    def check_silence(self):
        gone = self.silence.check(self.seconds_now())
        if gone:
            self.get_logger().warning(gone)


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = StatusMonitor()
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
