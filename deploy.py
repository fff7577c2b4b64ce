"""Provision the classroom: `pyinfra inventories/lab.py deploy.py` (add --dry --diff to preview).

Every host gets every step, in this order; a step is switched off with its
`<concern>_enabled: false` in the roster. A host that cannot get the ROS 2 the roster asks
for (not Ubuntu, wrong release, distro without packages) is stopped before anything changes.
At the end (also with --dry) roslab.reporting.summary prints one line per host: ok, changed, or
failed with the step and the reason; with class_lock_auto, a real run then writes the groups
classroom.lock lacks (roslab.class_lock_auto).
"""

from deploy.apt_cache import apt_cache_client, apt_cache_filled, apt_cache_server
from deploy.apt_ready import apt_lists, apt_ready
from deploy.class_lock_taken import class_lock_taken
from deploy.common import supported_host
from deploy.discovery import discovery_in_place
from deploy.locale import system_locale
from deploy.network import network
from deploy.profile_services import profile_services_in_place
from deploy.profile_switch import profile_switch_cleaned
from deploy.python_env import python_env
from deploy.robot_base import robot_base
from deploy.robot_profile import robot_profile
from deploy.ros_apt_source import ros_apt_source
from deploy.ros_install import ros_install
from deploy.rosdep import rosdep
from deploy.shell_env import shell_env
from deploy.sources import sources
from deploy.ssh_hardening import ssh_hardening
from deploy.ssh_identity import ssh_identity
from deploy.workspace import workspace
from roslab import pyinfra_planning, remote_files
from roslab.reporting import summary
from roslab.ros import colcon_progress
from roslab.ssh import keepalive as ssh_keepalive, run_lock, sudo

summary.install()  # once per run, although pyinfra runs this file once per host
sudo.install()  # for any inventory: the sudo password goes to an askpass file, never a command line
remote_files.install()  # every upload: one command, never through a link (roslab.remote_files)
ssh_keepalive.install()  # any inventory: a host that goes silent mid-step is lost in seconds (reconnections)
run_lock.install()  # one run at a time per host: every connection first takes the host's run lock
pyinfra_planning.install()  # pyinfra's operation order without reading source per operation (issue 32)
colcon_progress.install()  # a long colcon build says which package it is at (roslab.ros.colcon_progress)

if supported_host():
    # The cache host first: pyinfra runs each operation on every host before the next, so
    # the cache answers before any host's first apt-get update.
    apt_cache_server()
    apt_cache_client()
    apt_ready()
    ros_apt_source()
    apt_lists()  # one apt-get update, after every source above is written
    apt_cache_filled()  # one host per release downloads for the class before anyone installs
    system_locale()
    ros_install()
    robot_profile()  # udev rules and groups (its packages are ros_install's)
    robot_base()  # a TurtleBot 4's Create 3: usb0, chrony for it, its ROS settings over HTTP
    rosdep()
    python_env()  # the profile's venv, from the class's wheelhouse (before any workspace build)
    shell_env()
    discovery_in_place()  # the middleware's files, the team's discovery server or router (on its main)
    ssh_identity()
    ssh_hardening()  # only once a key login worked in this run
    # The address change takes effect here, after SSH is known good; the steps
    # after it run at the host's new address.
    network()
    sources()  # the underlay the workspace overlays (repositories fetched once by the controller)
    workspace()
    profile_services_in_place()  # the rover's service, the micro-ROS agent: after the build they run
    profile_switch_cleaned()  # an earlier profile's units and groups gone, the profile recorded
    class_lock_taken()  # last: class_lock_auto reads the versions of a group the lock lacks

summary.mark_planned()  # this host's plan is complete (a run that stops before is reported so)
