"""ROS 2 installed: the distro's desktop (main hosts) or ros-base (robots), dev tools, extras."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import DeployError, deploy
from pyinfra.operations import apt

from deploy.common import host_distro, setting, should_run, where
from roslab.distro import VARIANTS

DEFAULTS = {
    # Install the ROS 2 packages.
    "ros_install_enabled": True,
    # The Ubuntu release the roster expects; a host running another release is stopped.
    "ubuntu_release": "24.04",
    # ROS 2 distro; None: the release's default (noble: jazzy, jammy: humble).
    "ros_distro": None,
    # Variant to install (desktop, ros-base, ...); None: by role, see the next two keys.
    "ros_variant": None,
    # Variant for main hosts (with GUI: RViz, rqt, demos).
    "ros_variant_main": "desktop",
    # Variant for robots (no GUI).
    "ros_variant_robot": "ros-base",
    # Install ros-dev-tools (colcon, rosdep, vcstool).
    "ros_dev_tools": True,
    # Extra apt packages for every host; "{distro}" is replaced, e.g. "ros-{distro}-turtlesim".
    "ros_extra_packages": [],
}


def ros_packages(distro: str, role: str | None, data) -> list[str]:
    """The apt packages a host of this role gets, from its settings (`data`: a mapping)."""
    variant = data["ros_variant"] or (
        data["ros_variant_robot"] if role == "robot" else data["ros_variant_main"]
    )
    if variant not in VARIANTS:
        raise DeployError(
            f"{where()}: ROS 2 variant {variant!r} is unknown (known: {', '.join(VARIANTS)})"
        )
    extras = data["ros_extra_packages"] or []
    if isinstance(extras, str) or not all(isinstance(name, str) for name in extras):
        raise DeployError(f"{where()}: ros_extra_packages must be a list of package names")
    packages = [f"ros-{distro}-{variant}"]
    if data["ros_dev_tools"]:
        packages.append("ros-dev-tools")
    packages += [name.format(distro=distro) for name in extras]
    return packages


@deploy("ROS 2 is installed for the host's distro and role", data_defaults=DEFAULTS)
def ros_install():
    """Install ros-<distro>-<variant>, ros-dev-tools and the classroom's extra packages.

    Reads host.data: ros_install_enabled, ros_distro, ros_variant, ros_variant_main,
    ros_variant_robot, ros_dev_tools, ros_extra_packages, roslab_role, apt_lock_timeout.
    (ubuntu_release is checked by deploy.common.supported_host.)
    """
    if not should_run("ros_install_enabled"):
        return
    distro = host_distro()
    packages = ros_packages(
        distro, host.data.get("roslab_role"), {key: setting(key) for key in DEFAULTS}
    )
    apt.packages(
        name=f"Ensure ROS 2 {distro} is installed ({', '.join(packages)})",
        packages=packages,
        extra_install_args=f"-o DPkg::Lock::Timeout={setting('apt_lock_timeout')}",
    )
