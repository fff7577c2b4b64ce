"""ROS 2 installed: the distro's desktop (main hosts) or ros-base (robots), dev tools, extras."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy

from deploy.common import host_distro, should_run
from roslab import probe, settings
from roslab.operations import packages_installed
from roslab.quoting import apt_arguments

DEFAULTS = settings.defaults("ros_install")


def ros_packages(distro: str, role: str | None, data) -> list[str]:
    """The apt packages a host of this role gets, from its settings (`data`: a mapping).

    The variants and extra package names were checked by the schema (roslab.settings);
    `apt_arguments` refuses anything apt-get would read as an option all the same.
    """
    variant = data["ros_variant"] or (
        data["ros_variant_robot"] if role == "robot" else data["ros_variant_main"]
    )
    packages = [f"ros-{distro}-{variant}"]
    if data["ros_dev_tools"]:
        packages.append("ros-dev-tools")
    packages += [name.replace("{distro}", distro) for name in data["ros_extra_packages"] or []]
    return apt_arguments(packages)


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
    packages = ros_packages(distro, host.data.get("roslab_role"), host.data.dict())
    packages_installed(
        name=f"Ensure ROS 2 {distro} is installed ({', '.join(packages)})",
        packages=packages,
        lock_timeout=host.data.apt_lock_timeout,
    )


@probe.reader
def ros_install_reads() -> list:
    """What ros_install's operation reads on a host that needs no change."""
    return probe.packages_reads() if should_run("ros_install_enabled") else []
