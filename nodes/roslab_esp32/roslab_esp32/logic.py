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

"""The demo's arithmetic, without ROS: a potentiometer reading to a servo angle."""

# The ESP32's ADC reads 12 bits (analogRead: 0-4095); a hobby servo turns 0-180 degrees.
ADC_MAX = 4095
ANGLE_MAX = 180

POTENTIOMETER_TOPIC = '/esp32/potentiometer'
SERVO_ANGLE_TOPIC = '/esp32/servo_angle'


def servo_angle(raw):
    """Return the servo angle (0-180, whole degrees) for a raw reading (clamped to 0-4095)."""
    raw = min(max(int(raw), 0), ADC_MAX)
    return (raw * ANGLE_MAX + ADC_MAX // 2) // ADC_MAX
