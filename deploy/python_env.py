"""The robot profile's Python requirements in its venv, from the class's wheelhouse.

The controller downloads each requirement set once per class and host platform
(roslab/python_env/wheelhouse.py: wheels for the host's machine, glibc and Python, sdists where the
index has no wheel) and copies the files to WHEELHOUSE on each host that needs them (only
files that changed); the host installs from those alone (`pip install --no-index`), into a
venv with the system's site packages (ROS's Python stays importable) and a COLCON_IGNORE.
pip runs only when the requirement set or its files changed (a stamp in the venv).
"""

from __future__ import annotations

import posixpath
from io import StringIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.operations import apt, files, server
from pyinfra.operations.util import any_changed

from deploy.common import (
    as_login_user,
    existing_login_home,
    host_distro,
    login_home,
    login_user,
    should_run,
    stop_host,
    where,
)
from roslab import class_lock, class_lock_auto, probe, settings
from roslab.python_env import wheelhouse
from roslab.ops.apt import apt_install_options
from roslab.python_env.venv import (
    PythonTarget,
    python_target_reads,
    venv_requirements_installed,
    venv_requirements_installed_reads,
)
from roslab.quoting import shell_word
from roslab.host_settings import HostSettings, host_settings
from roslab.profiles.resolve import PythonEnv

DEFAULTS = settings.defaults("python_env")

WHEELHOUSE = "/var/cache/roslab/wheelhouse"  # on the host: root's, readable by the login user
REQUIREMENTS = f"{WHEELHOUSE}/requirements.txt"


def python_of(settings: HostSettings) -> PythonEnv:
    """A host's profile's Python environment (no venv, no requirements without a profile)."""
    profile = settings.roslab_profile
    return profile.python if profile is not None else PythonEnv(venv=None, requirements=[])


def profile_python() -> PythonEnv:
    """This host's profile's Python environment (no venv, no requirements without a profile)."""
    return python_of(host_settings(host))


def filled_venv(home: str) -> str | None:
    """The profile's venv under `home` (the login user's home, or "~") when this step fills
    it, else None: what the ~/.bashrc block and the units put on PYTHONPATH."""
    venv = profile_python().venv
    return posixpath.join(home, venv) if venv and host_settings(host).python_env_enabled else None


@probe.installs
def python_env_packages(settings: HostSettings, codename: str | None, python_sdist: bool = False) -> list[str]:
    """What this step installs (roslab.probe.installs): python3-venv where the profile has a venv,
    and python_sdist_build_packages where the host's wheelhouse holds an sdist (known once the
    controller has it: kept from an earlier run, or noted by this run's plan in
    `_roslab_python_sdist`, given as `python_sdist`; the class's apt cache is filled before this step plans, so on a
    class's very first run those packages reach the hosts through the cache as a proxy)."""
    python = python_of(settings)
    if not settings.python_env_enabled or not python.venv:
        return []
    packages = ["python3-venv"]
    if python.requirements and (python_sdist or any(
            kept.has_sdist for kept in wheelhouse.kept_for_any_target(
                python.requirements, settings.python_index_url, settings.python_wheelhouse_dir))):
        packages += [name for name in settings.python_sdist_build_packages or [] if name not in packages]
    return packages


@deploy("The robot profile's Python requirements are installed in its venv", data_defaults=DEFAULTS)
def python_env():
    """Make the profile's venv and install its pinned requirements from the class's wheelhouse.

    Reads host_settings(host): python_env_enabled, roslab_profile (its "python": venv, requirements),
    python_index_url, python_wheelhouse_dir, python_sdist_build_packages, offline, login_user,
    apt_lock_timeout.
    """
    typed = host_settings(host)
    if not should_run("python_env_enabled"):
        return
    python = profile_python()
    if not python.venv:  # the profile has no Python requirements or venv: nothing to do
        return
    user, home = login_user(), login_home()
    if home is None:
        return
    target = wheelhouse.Target(**host.get_fact(PythonTarget))
    if target.problem():
        stop_host(f"{where()}: python_packages: {target.problem()}; nothing was changed on it")
        return
    house = None
    if python.requirements:
        try:
            house = wheelhouse.wheelhouse(python.requirements, target, typed.python_index_url,
                                          typed.python_wheelhouse_dir, offline=typed.offline)
        except wheelhouse.WheelhouseError as error:
            stop_host(f"{where()}: python_packages: {error}; nothing was changed on it")
            return
        if not wheelhouse_meets_lock(house, target):
            return
        host.data._roslab_python_sdist = house.has_sdist

    apt.packages(
        name="Ensure Python's venv module is installed"
             + (" (and what building an sdist needs)" if house and house.has_sdist else ""),
        # this run's own note, made just above: the snapshot host_settings holds predates it
        packages=python_env_packages(typed, None, python_sdist=bool(house and house.has_sdist)),
        extra_install_args=apt_install_options(typed.apt_lock_timeout),
    )
    venv = posixpath.join(home, python.venv)
    if house is None:
        venv_requirements_installed(name=f"Ensure the venv {venv} exists", venv=venv, python=target.python,
                                    **as_login_user(user))
        return
    wheelhouse_on_host(house)
    venv_requirements_installed(
        name=f"Ensure {', '.join(python.requirements)} are installed in {venv}",
        venv=venv, python=target.python, wheelhouse=WHEELHOUSE, requirements_file=REQUIREMENTS,
        stamp=house.digest, **as_login_user(user),
    )


def wheelhouse_meets_lock(house: wheelhouse.Wheelhouse, target: wheelhouse.Target) -> bool:
    """Stop the host before anything is installed if a file of `house` has another sha256 than
    the class lock's for its name and version (the host's group: its distro and `uname -m`), in
    one line naming the file, both hashes and what to do; note the files for a lock this run
    takes (class_lock_auto). True: the host carries on."""
    typed = host_settings(host)
    locked = class_lock.lock_beside(typed.roslab_roster_path) is not None  # none: no distro read either
    group = class_lock.host_group(typed.roslab_roster_path, host_distro(), target.machine) if locked else None
    problems = class_lock.wheel_mismatches(group, house.files) if group is not None else []
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        stop_host(f"{where()}: python_packages: {problems[0]}{more}")
        return False
    if typed.class_lock_auto and typed.roslab_roster_path:
        class_lock_auto.note_wheels(typed.roslab_roster_path, host.name, house.files)
    return True


def wheelhouse_on_host(house: wheelhouse.Wheelhouse) -> None:
    """The class's wheelhouse `house` and its pinned requirements are on the host, in WHEELHOUSE
    and REQUIREMENTS; the files of an earlier requirement set are removed once one changed."""
    pushed = [
        files.put(name=f"Ensure {item.name} (from the class's wheelhouse) is on the host",
                  src=str(house.path / item.name), dest=f"{WHEELHOUSE}/{item.name}", mode="644")
        for item in house.files
    ]
    pushed.append(files.put(name="Ensure the pinned requirements are on the host",
                            src=StringIO(house.requirements_text), dest=REQUIREMENTS, mode="644"))
    keep = [item.name for item in house.files] + [posixpath.basename(REQUIREMENTS)]
    server.shell(
        name=f"Ensure {WHEELHOUSE} holds only this wheelhouse's files",
        commands=[remove_others_command(WHEELHOUSE, keep)],
        _if=any_changed(*pushed),
    )


def remove_others_command(folder: str, keep: list[str]) -> str:
    """Removes the files in `folder` not named in `keep` (a requirement set that changed)."""
    patterns = "|".join(shell_word(name) for name in keep)
    return (f"cd {shell_word(folder)} && for f in * .[!.]*; do [ -e \"$f\" ] || continue; "
            f"case \"$f\" in {patterns}) ;; *) rm -rf -- \"$f\" ;; esac; done")


@probe.reader
def python_env_reads() -> list:
    """What python_env's operations read on a host that needs no change."""
    if not should_run("python_env_enabled"):
        return []
    python = profile_python()
    home = existing_login_home()
    if not python.venv or home is None:
        return []
    reads = [*python_target_reads(), *probe.packages_reads(),
             *venv_requirements_installed_reads(posixpath.join(home, python.venv))]
    if python.requirements:
        # The files are known once the controller has the wheelhouse; its folder and the
        # requirements file always, the wheels through their names in a kept wheelhouse.
        reads += probe.put_reads(REQUIREMENTS)
        for name in _kept_file_names(python.requirements):
            reads += probe.put_reads(f"{WHEELHOUSE}/{name}")
    return reads


def _kept_file_names(requirements: list[str]) -> list[str]:
    """The files this host will get, when the controller already holds its wheelhouse.

    The probe runs before the host's platform is read, so the kept wheelhouses of these
    requirements for every platform are looked at (a name read in vain costs a line of the probe).
    """
    typed = host_settings(host)
    names: list[str] = []
    for kept in wheelhouse.kept_for_any_target(requirements, typed.python_index_url,
                                               typed.python_wheelhouse_dir):
        names += [item.name for item in kept.files if item.name not in names]
    return names
