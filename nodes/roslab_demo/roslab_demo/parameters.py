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

"""Declare a node's ROS parameters from the table in roslab_demo.logic."""

from rcl_interfaces.msg import ParameterDescriptor
from roslab_demo.logic import parameter_value, PARAMETERS


def declare_parameters(node, node_name):
    """
    Declare the parameters PARAMETERS lists for `node_name`; return their values.

    Values from a parameters file or the command line override the defaults.
    The nodes read their parameters once at start-up, so the parameters are
    read-only: `ros2 param set` then says so instead of silently doing nothing.

    Declared with dynamic typing, so that `publish_rate_hz: 2` (an integer where the
    default is a float) reaches logic.parameter_value, which takes it as 2.0, instead
    of rclpy killing the node with InvalidParameterTypeException; a value of the wrong
    kind (text for a number) is refused there, naming the parameter.
    """
    table = PARAMETERS[node_name]
    node.declare_parameters('', [
        (name, spec.default, ParameterDescriptor(
            description=spec.description, read_only=True, dynamic_typing=True))
        for name, spec in table.items()
    ])
    return {name: parameter_value(node_name, name, node.get_parameter(name).value)
            for name in table}
