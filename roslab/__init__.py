"""roslab: provision ROS 2 onto a classroom of Raspberry Pis with pyinfra."""

__version__ = "0.1.0"
