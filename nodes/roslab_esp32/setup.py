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

from setuptools import setup

package_name = 'roslab_esp32'

setup(
    name=package_name,
    version='0.1.0',
    packages=[package_name],
    data_files=[
        # The marker that lets ROS tools (ros2 run, ros2 pkg) find the package.
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='roslab maintainers',
    maintainer_email='roslab@example.com',
    description='roslab ESP32 micro-ROS demo: potentiometer in, servo angle out.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'servo_follower = roslab_esp32.servo_follower:main',
        ],
    },
)
