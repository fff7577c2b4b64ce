"""ROS 2 itself: the release records, discovery and the environment, rosdep's data, the colcon workspace."""
