"""A profile's Python requirements: refused before connecting unless pinned, downloaded once per
class and platform into the controller's wheelhouse, installed on a host from the pushed files
only, and a second run changes nothing."""

from __future__ import annotations

import io
import json
import tarfile
import textwrap
from pathlib import Path

import pytest
from fixtures.classroom import typed
from fixtures.fake_host import plan
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import Directory, File, Sha1File
from pyinfra.facts.server import Home, LinuxDistribution, User

from deploy import python_env as deploy_python
from roslab import probe, settings
from roslab.python_env import wheelhouse
from roslab.python_env.venv import STAMP, PythonTarget, VenvState, venv_requirements_installed
from roslab.roster import RosterError, load_roster

OSR_LIKE = ["adafruit-circuitpython-servokit==1.3.17", "ina260==0.0.3", "RPi.GPIO==0.7.1", "smbus==1.1.post2"]
PI = wheelhouse.Target("aarch64", "2.39", "3.12")


@pytest.fixture(autouse=True)
def _fresh_run(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)
    monkeypatch.setattr(wheelhouse, "_this_run", {})  # each test is a run of its own


def roster(tmp_path: Path, robot_side: str, extra: str = "") -> Path:
    side = textwrap.indent(textwrap.dedent(robot_side).strip(), " " * 14)
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent(f"""\
        classroom:
          ssh_user: ubuntu
          ros_packages_check: false
          python_wheelhouse_dir: wheels
        {extra}
        profiles:
          rover:
            distros: [jazzy, humble]
            robot:
        """) + side + textwrap.dedent("""
        teams:
          t1:
            robot_profile: rover
            hosts:
              t1-robot: {role: robot}
        """))
    return path


def errors_of(path: Path) -> list[str]:
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    return [str(problem) for problem in raised.value.problems]


# --- the roster: pinned or refused, before any host is touched ------------------------------

def test_pinned_requirements_resolve_into_the_hosts_profile_data(tmp_path):
    path = roster(tmp_path, f"python_packages: {json.dumps(OSR_LIKE)}\npython_venv: osr_venv")
    (robot,) = load_roster(path).hosts
    assert robot.data["roslab_profile"]["python"] == {"venv": "osr_venv", "requirements": OSR_LIKE}
    assert robot.data["python_wheelhouse_dir"] == str(tmp_path / "wheels")


def test_a_venv_is_named_after_the_profile_when_the_profile_names_none(tmp_path):
    (robot,) = load_roster(roster(tmp_path, "python_packages: [smbus==1.1.post2]")).hosts
    assert robot.data["roslab_profile"]["python"] == {"venv": "rover_venv", "requirements": ["smbus==1.1.post2"]}


@pytest.mark.parametrize(("requirement", "says"), [
    ("ina260", "'ina260' is not pinned: write ina260==<version>"),
    ("ina260>=0.0.3", "does not start with a Python package name"),
    ("ina260==0.*", "is not one exact release"),
    ("ina260==0.0.3; python_version<'3'", "is not one exact release"),
    ("ina260==0.0.3 --index-url http://evil/", "is not one exact release"),
    ("--index-url=http://evil/ x==1", "does not start with a Python package name"),
    ("ina260[extra]==0.0.3", "does not start with a Python package name"),
    ("git+https://evil/x.git", "does not start with a Python package name"),
    ("ina260==0.0.3\nsmbus", "must be a single line"),
])
def test_an_unpinned_or_hostile_requirement_is_refused_naming_file_profile_and_field(tmp_path, requirement, says):
    path = roster(tmp_path, f"python_packages: [{json.dumps(requirement)}]")
    error = errors_of(path)[0]  # then: the team's profile is unknown (it was refused)
    assert error.startswith("lab.yaml:10: field 'profiles.rover.robot.python_packages': "), error
    assert says in error


def test_one_project_pinned_twice_is_refused(tmp_path):
    error = errors_of(roster(tmp_path, "python_packages: [smbus==1.1.post2, SMBus==1.1]"))[0]
    assert "names 'smbus' twice" in error


@pytest.mark.parametrize("venv", ["/opt/venv", "../escape", "venvs/../../x", ".hidden", "a b", "$(id)", "~"])
def test_a_venv_outside_the_login_users_home_is_refused(tmp_path, venv):
    error = errors_of(roster(tmp_path, f"python_venv: {json.dumps(venv)}"))[0]
    assert "field 'profiles.rover.robot.python_venv'" in error


def test_an_extending_profile_repins_a_requirement_instead_of_adding_a_second(tmp_path):
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent("""\
        classroom: {ssh_user: ubuntu, ros_packages_check: false}
        profiles:
          base: {distros: [jazzy], robot: {python_packages: [smbus==1.1, ina260==0.0.3]}}
          newer: {extends: base, robot: {python_packages: [smbus==1.1.post2]}}
        teams:
          t1:
            robot_profile: newer
            hosts: {t1-robot: {role: robot}}
        """))
    (robot,) = load_roster(path).hosts
    assert robot.data["roslab_profile"]["python"]["requirements"] == ["smbus==1.1.post2", "ina260==0.0.3"]


def test_the_index_and_the_wheelhouse_are_checked_where_they_are_declared():
    assert settings.check_value(settings.SETTINGS["python_index_url"], "file:///srv/simple")
    assert settings.check_value(settings.SETTINGS["python_wheelhouse_dir"], "/etc/wheels")
    assert settings.SETTINGS["python_index_url"].default == "https://pypi.org/simple"


# --- the controller's download, once per class and platform ---------------------------------

def test_the_download_is_for_the_hosts_platform_not_the_controllers(tmp_path):
    command = wheelhouse.pip_download_command(PI, "https://pypi.org/simple", tmp_path, ["ina260==0.0.3"])
    text = " ".join(command[1:])
    assert "-m pip download" in text and "--index-url https://pypi.org/simple" in text
    assert "--only-binary=:all: --platform manylinux_2_39_aarch64 --platform linux_aarch64" in text
    assert "--implementation cp --python-version 3.12" in text
    assert command[-1] == "ina260==0.0.3"
    assert "--trusted-host" not in command  # https: pip checks the certificate
    mirror = wheelhouse.pip_download_command(PI, "http://10.0.0.5:3141/root/pypi/+simple", tmp_path, ["x==1"])
    assert mirror[mirror.index("--trusted-host") + 1] == "10.0.0.5:3141"  # the teacher's http mirror
    sdist = wheelhouse.pip_download_command(PI, "https://pypi.org/simple", tmp_path, ["smbus==1.1.post2"], sdist=True)
    assert "--no-binary=:all:" in sdist and "--no-deps" in sdist and "--platform" not in sdist


def sdist_bytes(name: str, pyproject: str | None) -> bytes:
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz") as archive:
        for member, text in {f"{name}/setup.py": "", f"{name}/pyproject.toml": pyproject}.items():
            if text is None:
                continue
            info = tarfile.TarInfo(member)
            info.size = len(text.encode())
            archive.addfile(info, io.BytesIO(text.encode()))
    return out.getvalue()


class FakePip:
    """pip download as an index with wheels for some projects and only sdists for others."""

    def __init__(self, sdist_only=("RPi.GPIO", "smbus"), missing=()):
        self.calls: list[list[str]] = []
        self.sdist_only, self.missing = sdist_only, missing

    def __call__(self, command):
        self.calls.append(command)
        dest = Path(command[command.index("--dest") + 1])
        last = max(index for index, arg in enumerate(command) if arg.startswith("-"))
        wanted = command[last + (2 if command[last] == "--python-version" else 1):]
        for requirement in wanted:
            name = requirement.split("==")[0].split(">=")[0]
            if name in self.missing:
                return False, f"ERROR: Could not find a version that satisfies the requirement {requirement}\n"
            if "--no-binary=:all:" in command:
                (dest / f"{name}-{requirement.split('==')[1]}.tar.gz").write_bytes(sdist_bytes(name, None))
            elif name in self.sdist_only:
                return False, f"ERROR: Could not find a version that satisfies the requirement {requirement}\n"
            else:
                version = requirement.split("==")[1] if "==" in requirement else "99.0"
                (dest / f"{name.replace('-', '_')}-{version}-py3-none-any.whl").write_bytes(b"wheel " + name.encode())
        return True, ""


def test_each_requirement_set_is_downloaded_once_and_kept(tmp_path, monkeypatch):
    pip = FakePip()
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    first = wheelhouse.wheelhouse(OSR_LIKE, PI, "https://pypi.org/simple", tmp_path)
    calls = len(pip.calls)
    again = wheelhouse.wheelhouse(OSR_LIKE, PI, "https://pypi.org/simple", tmp_path)  # the next host
    assert len(pip.calls) == calls and again is first
    monkeypatch.setattr(wheelhouse, "_this_run", {})  # the next run
    kept = wheelhouse.wheelhouse(OSR_LIKE, PI, "https://pypi.org/simple", tmp_path)
    assert len(pip.calls) == calls and kept.digest == first.digest
    names = [item.name for item in first.files]
    assert "RPi.GPIO-0.7.1.tar.gz" in names and "smbus-1.1.post2.tar.gz" in names and first.has_sdist
    # No pyproject.toml in the sdists: pip's default build backend is downloaded for the host too.
    assert "setuptools-99.0-py3-none-any.whl" in names and "wheel-99.0-py3-none-any.whl" in names


def test_another_platform_is_another_download(tmp_path, monkeypatch):
    pip = FakePip()
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    pi = wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    pc = wheelhouse.wheelhouse(["ina260==0.0.3"], wheelhouse.Target("x86_64", "2.36", "3.11"),
                               "https://pypi.org/simple", tmp_path)
    assert pi.path != pc.path and len(pip.calls) == 2
    assert "manylinux_2_36_x86_64" in pip.calls[1] and "3.11" in pip.calls[1]


def test_offline_uses_only_the_wheelhouse(tmp_path, monkeypatch):
    pip = FakePip()
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    with pytest.raises(wheelhouse.WheelhouseError, match="offline, and the controller's wheelhouse has no"):
        wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path, offline=True)
    assert pip.calls == []
    wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    monkeypatch.setattr(wheelhouse, "_this_run", {})
    calls = len(pip.calls)
    assert wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path, offline=True).files
    assert len(pip.calls) == calls


def test_a_failed_download_names_the_requirement_keeps_nothing_and_is_remembered(tmp_path, monkeypatch):
    pip = FakePip(missing=("ina260",))
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    with pytest.raises(wheelhouse.WheelhouseError) as raised:
        wheelhouse.wheelhouse(["smbus==1.1.post2", "ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    assert "pip could not download ina260==0.0.3 for Python 3.12 on aarch64 (glibc 2.39)" in str(raised.value)
    calls = len(pip.calls)
    with pytest.raises(wheelhouse.WheelhouseError):  # the next host of the class waits for nothing
        wheelhouse.wheelhouse(["smbus==1.1.post2", "ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    assert len(pip.calls) == calls
    assert [path.name for path in tmp_path.rglob("*") if path.is_file()] == []  # no half wheelhouse


def test_a_damaged_kept_file_is_downloaded_again(tmp_path, monkeypatch):
    pip = FakePip()
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    house = wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    (house.path / house.files[0].name).write_bytes(b"truncated")
    monkeypatch.setattr(wheelhouse, "_this_run", {})
    again = wheelhouse.wheelhouse(["ina260==0.0.3"], PI, "https://pypi.org/simple", tmp_path)
    assert (again.path / again.files[0].name).read_bytes() != b"truncated"


def test_an_sdists_declared_build_backend_is_what_is_downloaded(tmp_path):
    path = tmp_path / "x-1.tar.gz"
    path.write_bytes(sdist_bytes("x-1", '[build-system]\nrequires = ["flit_core>=3.2,<4"]\n'))
    assert wheelhouse.build_requires(path) == ["flit_core>=3.2,<4"]
    path.write_bytes(sdist_bytes("x-1", '[build-system]\nrequires = ["--index-url=http://evil/"]\n'))
    with pytest.raises(wheelhouse.WheelhouseError, match="is not a list of requirements"):
        wheelhouse.build_requires(path)
    path.write_bytes(sdist_bytes("x-1", '[build-system]\nrequires = []\nbuild-backend = "b"\n'))
    assert wheelhouse.build_requires(path) == []


# --- the host: facts in, commands out ---------------------------------------------------------

def host_facts(venv_state: dict, files: dict, installed=("python3-venv", "python3-dev", "gcc")) -> dict:
    return {
        PythonTarget: {"machine": "aarch64", "glibc": "2.39", "python": "3.12"},
        Home: "/home/ubuntu", User: "ubuntu",
        LinuxDistribution: {"release_meta": {"ID": "ubuntu", "UBUNTU_CODENAME": "noble"}},
        DebPackages: {name: ["1.0"] for name in installed},
        VenvState: lambda path: venv_state,
        File: lambda path: {"size": 1, "mode": 644, "user": "root", "group": "root"} if path in files else None,
        Directory: lambda path: {"mode": 755} if path == deploy_python.WHEELHOUSE else None,
        Sha1File: lambda path: files.get(path),
    }


def host_data(tmp_path, requirements=("ina260==0.0.3", "smbus==1.1.post2")) -> dict:
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    # a whole resolved profile (host_settings reads every key), with these requirements
    profile, _ = resolve_host(builtin_profiles()["demo"], {}, distro="jazzy", role="robot")
    return {**settings.defaults("python_env"), "login_user": "ubuntu", "apt_lock_timeout": 600,
            "python_wheelhouse_dir": str(tmp_path / "wheels"), "offline": False,
            "roslab_profile": {**profile, "python": {"venv": "osr_venv", "requirements": list(requirements)}}}


def test_first_run_pushes_installs_as_the_login_user_and_second_run_changes_nothing(tmp_path, monkeypatch):
    import hashlib

    monkeypatch.setattr(wheelhouse, "_run_pip", FakePip())
    data = host_data(tmp_path)
    first = plan(deploy_python.python_env, host_facts({"python": None, "colcon_ignore": False, "stamp": ""}, {},
                                                      installed=()), data)
    assert not first.failed, first.errors
    changing = first.changing()
    apt = next(commands for name, commands in changing.items() if "venv module" in name)
    assert apt[0].endswith("install -o DPkg::Lock::Timeout=600 -- python3-venv python3-dev gcc")  # an sdist: its build needs a compiler
    uploads = first.uploads()
    assert set(uploads) >= {"/var/cache/roslab/wheelhouse/smbus-1.1.post2.tar.gz",
                            "/var/cache/roslab/wheelhouse/ina260-0.0.3-py3-none-any.whl"}
    assert uploads[deploy_python.REQUIREMENTS] == "ina260==0.0.3\nsmbus==1.1.post2\n"
    venv_op = first.operation("are installed in /home/ubuntu/osr_venv")
    assert venv_op.arguments.get("_sudo_user") == "ubuntu"
    commands = venv_op.text()
    assert commands[0] == "python3 -m venv --system-site-packages /home/ubuntu/osr_venv"
    assert commands[1] == "touch /home/ubuntu/osr_venv/COLCON_IGNORE"
    assert ("/home/ubuntu/osr_venv/bin/python -m pip install --no-index --find-links /var/cache/roslab/wheelhouse "
            "-r /var/cache/roslab/wheelhouse/requirements.txt") in commands[2]

    house = wheelhouse.wheelhouse(list(data["roslab_profile"]["python"]["requirements"]), wheelhouse.Target(
        "aarch64", "2.39", "3.12"), data["python_index_url"], data["python_wheelhouse_dir"])
    on_host = {f"{deploy_python.WHEELHOUSE}/{item.name}": hashlib.sha1(house.read(item.name)).hexdigest()
               for item in house.files}
    on_host[deploy_python.REQUIREMENTS] = hashlib.sha1(house.requirements_text.encode()).hexdigest()
    def probed_run():  # as deploy.common.supported_host does: the home, then every registered read
        probe.read_ahead([probe.read(Home, user="ubuntu")], _sudo=False)
        probe.read_ahead(deploy_python.python_env_reads())
        deploy_python.python_env()

    second = plan(probed_run, host_facts({"python": "3.12", "colcon_ignore": True, "stamp": house.digest}, on_host),
                  data)
    assert second.changing() == {}, second.changing()
    # A no-op run reads nothing outside the probe: the kept wheelhouse names the files to look at.
    assert second.facts_asked == ["HostProbe", "HostProbe"], second.facts_asked
    assert "/home/ubuntu/osr_venv (Python 3.12) already holds this requirement set" in second.noops


def test_a_changed_requirement_set_reinstalls_and_clears_the_old_files(tmp_path, monkeypatch):
    monkeypatch.setattr(wheelhouse, "_run_pip", FakePip())
    facts = host_facts({"python": "3.12", "colcon_ignore": True, "stamp": "0" * 64},
                       {f"{deploy_python.WHEELHOUSE}/ina260-0.0.2-py3-none-any.whl": "0" * 40})
    result = plan(deploy_python.python_env, facts, host_data(tmp_path, ["ina260==0.0.3"]))
    changing = result.changing()
    cleanup = next(commands for name, commands in changing.items() if "holds only" in name)
    assert "ina260-0.0.3-py3-none-any.whl|requirements.txt) ;; *) rm -rf" in cleanup[0]
    assert "pip install --no-index" in result.operation("Ensure ina260==0.0.3 are installed in").text()[-1]
    # No sdist: no compiler.
    assert not any("python3-dev" in " ".join(commands) for commands in changing.values())


def test_a_download_failure_stops_only_that_host_naming_the_requirement(tmp_path, monkeypatch):
    monkeypatch.setattr(wheelhouse, "_run_pip", FakePip(missing=("ina260",)))
    result = plan(deploy_python.python_env, host_facts({"python": None, "colcon_ignore": False, "stamp": ""}, {}),
                  host_data(tmp_path))
    assert result.failed and result.operations == []
    assert "python_packages: pip could not download ina260==0.0.3" in " ".join(result.errors)


def test_a_host_without_glibc_or_python_is_stopped_before_any_download(tmp_path, monkeypatch):
    pip = FakePip()
    monkeypatch.setattr(wheelhouse, "_run_pip", pip)
    facts = host_facts({}, {})
    facts[PythonTarget] = {"machine": "aarch64", "glibc": "none", "python": "3.12"}
    result = plan(deploy_python.python_env, facts, host_data(tmp_path))
    assert result.failed and pip.calls == []
    assert "is not glibc" in " ".join(result.errors)


def test_a_failing_install_is_one_roslab_line_naming_pips_error(tmp_path):
    from roslab.python_env.venv import pip_install_command
    import subprocess

    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin/python").write_text("#!/bin/sh\necho 'ERROR: Failed building wheel for RPi.GPIO' >&2; exit 1\n")
    (venv / "bin/python").chmod(0o755)
    done = subprocess.run(["sh", "-c", pip_install_command(str(venv), "/nonexistent", "/nonexistent/r.txt", "ab")],
                          capture_output=True, text=True)
    assert done.returncode == 1
    assert f"roslab: pip could not install the requirements into {venv}: ERROR: Failed building wheel for RPi.GPIO" \
        in done.stderr
    assert not (venv / STAMP).exists()  # the next run tries again


def test_a_venv_of_another_python_is_made_again(tmp_path):
    result = plan(venv_requirements_installed, {VenvState: {"python": "3.10", "colcon_ignore": True, "stamp": "x"}},
                  venv="/home/ubuntu/osr_venv", python="3.12", wheelhouse="/w", requirements_file="/w/r.txt",
                  stamp="x")
    commands = result.operations[0].text()
    assert commands[:2] == ["rm -rf -- /home/ubuntu/osr_venv",
                            "python3 -m venv --system-site-packages /home/ubuntu/osr_venv"]
    assert "pip install" in commands[-1]


# The sandbox's stand-in index end to end (the controller's real `pip download`, each file fetched
# once, venvs that import the packages, sdists built by pip) is tests/e2e/test_python_env_e2e.py's:
# a real pip download and venv install took 29 s here, no unit test's cost.


def test_a_venv_that_would_hold_the_workspace_is_refused(tmp_path):
    errors = errors_of(roster(tmp_path, "python_venv: ros2_ws"))  # the default workspace_dir
    assert "puts its Python venv in ~/ros2_ws, which holds the workspace" in errors[0]
    errors = errors_of(roster(tmp_path, "python_venv: labs", extra="  workspace_dir: ~/labs/ros2_ws"))
    assert "which holds the workspace (workspace_dir ~/labs/ros2_ws)" in errors[0]


def test_the_class_cache_learns_the_build_packages_from_a_kept_wheelhouse(tmp_path, monkeypatch):
    monkeypatch.setattr(wheelhouse, "_run_pip", FakePip())
    data = host_data(tmp_path)
    assert deploy_python.python_env_packages(typed(data), "noble") == ["python3-venv"]  # nothing known yet
    wheelhouse.wheelhouse(data["roslab_profile"]["python"]["requirements"], PI, data["python_index_url"],
                          data["python_wheelhouse_dir"])
    assert deploy_python.python_env_packages(typed(data), "noble") == ["python3-venv", "python3-dev", "gcc"]
    assert deploy_python.python_env_packages(typed({**data, "python_env_enabled": False}), "noble") == []


def test_a_wheel_whose_hash_differs_from_the_class_lock_stops_the_host_before_anything_is_installed(
        tmp_path, monkeypatch):
    from pyinfra.facts.server import Arch

    from roslab import class_lock

    monkeypatch.setattr(wheelhouse, "_run_pip", FakePip())
    data = {**host_data(tmp_path, ["ina260==0.0.3"]), "roslab_roster_path": str(tmp_path / "classroom.yaml")}
    house = wheelhouse.wheelhouse(["ina260==0.0.3"], PI, data["python_index_url"], data["python_wheelhouse_dir"])
    (wheel,) = house.files
    facts = {**host_facts({"python": None, "colcon_ignore": False, "stamp": ""}, {}), Arch: "aarch64"}

    def with_lock(sha256: str):
        group = class_lock.LockedGroup("2026-11-28T22:00:00Z", "robot1",
                                       wheels={"ina260": class_lock.LockedWheel("0.0.3", sha256)})
        (tmp_path / "classroom.lock").write_text(class_lock.render_lock(class_lock.ClassLock({"jazzy/arm64": group})))
        return plan(deploy_python.python_env, facts, data)

    stopped = with_lock("0" * 64)
    assert stopped.failed and stopped.operations == []
    assert (f"python_packages: {wheel.name} has sha256 {wheel.sha256} in the class's wheelhouse but the class lock "
            f"has {'0' * 64} for ina260 0.0.3: nothing was installed; put the locked file back in the wheelhouse, "
            "or take the new one with `roslab lock --update`") in " ".join(stopped.errors)
    met = with_lock(wheel.sha256)
    assert not met.failed and "pip install --no-index" in met.operation("ina260==0.0.3 are installed in").text()[-1]
