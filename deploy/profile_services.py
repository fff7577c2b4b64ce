"""A robot profile's own services (the rover's `osr_startup`, the `micro_ros_agent`): one unit
each, run as the login user with the distro's, the underlay's and the workspace's setup, the
host's ROS environment and the service's own variables (RMW_IMPLEMENTATION for the agent).

A service whose `enabled_if` settings do not hold (the rover before `osr_calibrated: true`, a
board not yet `esp32_present`) is installed, stopped and disabled, saying why. A service the
profile no longer names (a team switched profile) is stopped, disabled and removed by
deploy/profile_switch.py, which finds it by MANAGED_MARK. Runs after the workspace, whose build
the commands use.
"""

from __future__ import annotations

import posixpath
from io import StringIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.facts.files import File, FileContents
from pyinfra.operations import files, systemd

from deploy.common import existing_login_home, host_distro, login_user, should_run, stop_host, where
from deploy.python_env import filled_venv
from roslab import probe, settings
from roslab.ros import workspace as ws_ops
from roslab.ops.systemd import service_installed_not_running
from roslab.python_env.venv import venv_on_pythonpath
from roslab.quoting import shell_word, systemd_value
from roslab.service_units import NODE_RESTARTS, unit_values
from roslab.ros.environment import host_environment
from roslab.templating import render
from roslab.host_settings import host_settings
from roslab.profiles.resolve import ResolvedService

DEFAULTS = settings.defaults("profile_services")
UNIT_DIR = "/etc/systemd/system"


def unit_path(name: str) -> str:
    return posixpath.join(UNIT_DIR, f"{name}.service")


def profile_services() -> list[ResolvedService]:
    profile = host_settings(host).roslab_profile
    return profile.services if profile is not None else []


def exec_script(*, distro: str, workspace_dir: str, command: str, venv_dir: str | None = None) -> str:
    """The bash script the unit runs: the distro's setup, the workspace's (which overlays the
    profile's underlay) when it was built, the profile's venv on PYTHONPATH (`venv_dir`,
    absolute, or None), then the command (its settings already shell words)."""
    setup = posixpath.join(workspace_dir, "install", "setup.bash")
    return " && ".join([
        f"source {shell_word(f'/opt/ros/{distro}/setup.bash')}",
        f"if [ -f {shell_word(setup)} ]; then source {shell_word(setup)}; fi",
        *([venv_on_pythonpath(shell_word(venv_dir))] if venv_dir else []),
        f"exec {command}",
    ])


def host_filled(service_environment: dict[str, str], environment: dict[str, str]) -> dict[str, str]:
    """A service's own variables with the host's placeholders filled: ${ros_domain_id} is the
    host's ROS_DOMAIN_ID (a variable that names it is left out on a host without one)."""
    domain = environment.get("ROS_DOMAIN_ID")
    filled = {}
    for name, text in service_environment.items():
        if "${ros_domain_id}" in text:
            if domain is None:
                continue
            text = text.replace("${ros_domain_id}", domain)
        filled[name] = text
    return filled


def unit_text(*, service: ResolvedService, profile: str, user: str, home: str, workspace_dir: str, distro: str,
              environment: dict[str, str], venv_dir: str | None = None) -> str:
    """templates/profile-service.service.j2 with every value written for systemd."""
    script = exec_script(distro=distro, workspace_dir=workspace_dir, command=service.command,
                         venv_dir=venv_dir)
    merged = {**environment, **host_filled(service.environment, environment)}
    return render(
        "profile-service.service.j2",
        profile=systemd_value(profile),
        service=f"{service.name}.service",
        description=systemd_value(service.description),
        **unit_values(user=user, home=home, environment=merged, script=script, restarts=NODE_RESTARTS),
    )


@deploy("The robot profile's services are installed, and run where the roster says so",
        data_defaults=DEFAULTS)
def profile_services_in_place():
    """Write each service of the host's profile side as a unit; enable and start it when its
    `enabled_if` holds, else stop and disable it (saying why).

    Reads host_settings(host): profile_services_enabled, roslab_profile (name, services, python),
    python_env_enabled, workspace_dir, login_user, ssh_user, ros_distro and what
    roslab.ros.environment.host_environment reads.
    """
    typed = host_settings(host)
    services, resolved = profile_services(), typed.roslab_profile
    if not services or resolved is None or not should_run("profile_services_enabled"):
        return  # no services without a profile (profile_services)
    home = existing_login_home()
    if home is None:
        stop_host(f"{where()}: profile services: the login user {login_user()!r} does not exist; "
                  "nothing was changed by this step")
        return
    user, distro = login_user(), host_distro()
    name = resolved.name
    workspace_dir = ws_ops.workspace_path(home, typed.workspace_dir)
    try:  # before any change: a value a unit cannot carry stops this host only
        units = {service.name: unit_text(
            service=service, profile=name, user=user, home=home, workspace_dir=workspace_dir, distro=distro,
            environment=host_environment(typed, distro),
            venv_dir=filled_venv(home)) for service in services}
    except ValueError as error:
        stop_host(f"{where()}: profile services: {error}; nothing was changed by this step")
        return
    foreign = [service.name for service in services if not ours_to_write(service.name)]
    if foreign:
        stop_host(f"{where()}: profile services: {', '.join(f'{name}.service' for name in foreign)} is a unit "
                  f"of this host that roslab did not write (a package's, or someone's own): robot profile {name} "
                  "will not replace it; rename the profile's service; nothing was changed by this step")
        return
    for service in services:
        unit_name = f"{service.name}.service"
        unit = files.put(
            name=f"Ensure {unit_name} runs {service.command} as {user} (robot profile {name})",
            src=StringIO(units[service.name]), dest=unit_path(service.name),
            user="root", group="root", mode="644",
        )
        systemd.daemon_reload(name=f"Ensure systemd has read the changed {unit_name}", _if=unit.did_change)
        if service.enabled:
            systemd.service(name=f"Ensure {unit_name} is enabled and running", service=unit_name,
                            enabled=True, running=True)
            systemd.service(name=f"Ensure {unit_name} runs its current unit", service=unit_name,
                            restarted=True, _if=unit.did_change)
        else:
            service_installed_not_running(
                name=f"Ensure {unit_name} is stopped and disabled ({service.disabled_because})",
                service=unit_name, because=service.disabled_because)


MANAGED_MARK = "# managed by roslab (deploy/profile_services.py)"
PACKAGE_UNIT_DIRS = ("/usr/lib/systemd/system", "/lib/systemd/system")


def ours_to_write(name: str) -> bool:
    """Whether roslab may write `<name>.service` in /etc/systemd/system: no package ships a unit
    of that name, and the file there is missing or one roslab wrote."""
    if any(host.get_fact(File, path=posixpath.join(folder, f"{name}.service")) for folder in PACKAGE_UNIT_DIRS):
        return False
    current = host.get_fact(FileContents, path=unit_path(name))
    return current is None or bool(current) and current[0].startswith(MANAGED_MARK)


@probe.reader
def profile_services_reads() -> list:
    """What profile_services_in_place's operations read on a host that needs no change."""
    services = profile_services()
    if not services or not should_run("profile_services_enabled") or existing_login_home() is None:
        return []
    reads = []
    for service in services:
        reads += [*probe.put_reads(unit_path(service.name)), *probe.service_reads(f"{service.name}.service"),
                  probe.read(FileContents, path=unit_path(service.name)),
                  *(probe.read(File, path=posixpath.join(folder, f"{service.name}.service"))
                    for folder in PACKAGE_UNIT_DIRS)]
    return reads
