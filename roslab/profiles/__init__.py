"""Robot profiles: what a team's robot and its main run, as data (like Clearpath's robot.yaml).

A profile is a YAML file: the distros it supports, its own settings (allowed values,
required or with a default), and per side (`main`, `robot`) the ROS packages (ROS names,
checked against the distro's rosdistro file), apt packages, environment variables, the
login user's groups, devices (roslab writes their udev rules), the launch the host's service runs and a checklist of
steps that need the hardware attached; `when` blocks add to a side for some setting
values (the lidar's driver for `lds_model`). Built-in profiles ship as package data
(`roslab/profiles/data/*.yaml`); a roster may define its own under `profiles:` or extend a
built-in one (`extends: turtlebot3`). Both are checked by `schema.py` before any host is
touched, and `resolve.py` turns a host's profile and settings into plain host data
(`roslab_profile`) that the deploys read.

    schema.py    parse and check one profile mapping (problems with file:line)
    library.py   the built-in profiles, a roster's own, `extends` (in any order; loops named)
    resolve.py   a host's profile: packages, environment, udev rules... for its side and distro
    devices.py   the devices a profile declares (kinds, ids, groups allow-listed) and the udev rules roslab writes for them
    packages.py  every ROS package a host will install, checked against rosdistro
"""
