"""Provision the classroom: `pyinfra inventories/lab.py deploy.py` (add --dry --diff to preview).

Every host gets every step, in this order; a step is switched off with its
`<concern>_enabled: false` in the roster. A host that cannot get the ROS 2 the roster asks
for (not Ubuntu, wrong release, distro without packages) is stopped before anything changes.
At the end (also with --dry) roslab.summary prints one line per host: ok, changed, or
failed with the step and the reason.
"""

from deploy.apt_ready import apt_ready
from deploy.common import supported_host
from deploy.locale import system_locale
from deploy.network import network
from deploy.ros_apt_source import ros_apt_source
from deploy.ros_install import ros_install
from deploy.rosdep import rosdep
from deploy.shell_env import shell_env
from deploy.ssh_identity import ssh_identity
from deploy.workspace import workspace
from roslab import summary

summary.install()  # once per run, although pyinfra runs this file once per host

if supported_host():
    apt_ready()
    system_locale()
    ros_apt_source()
    ros_install()
    rosdep()
    shell_env()
    ssh_identity()
    # The address change takes effect here, after SSH is known good; the steps
    # after it run at the host's new address.
    network()
    workspace()

summary.mark_planned()  # this host's plan is complete (a run that stops before is reported so)
