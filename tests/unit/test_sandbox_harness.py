"""The sandbox harness without hosts: names, the classroom plan, the roster it writes,
the Ubuntu emulation files, and the upstream's rosdep/rosdistro data and stand-ins.
"""

from __future__ import annotations

import errno
import ipaddress
import subprocess
import stat
import textwrap
from pathlib import Path

import pytest
import rosdistro
import yaml

from roslab import settings
from roslab.roster import inventory_groups, load_roster
from roslab.sandbox import emulation, hosts, image, lifecycle, seeding, upstream
from roslab.sandbox.instance import Instance, default_subnet
from roslab.sandbox.system import SandboxError

URL = "http://10.213.0.1:8080"


@pytest.fixture(autouse=True)
def _no_sandbox_env(monkeypatch):
    monkeypatch.delenv("ROSLAB_SANDBOX", raising=False)
    monkeypatch.delenv("ROSLAB_SANDBOX_SUBNET", raising=False)


# -- instances -----------------------------------------------------------------------------

def test_default_instance_uses_the_documented_subnet():
    instance = Instance.from_env()
    assert (instance.name, str(instance.subnet)) == ("roslab", "10.213.0.0/24")
    assert instance.bridge_address == "10.213.0.1"
    assert instance.roster_path == Path("/run/roslab/sandbox/roslab/roster.yaml")


def test_other_instances_get_their_own_subnet_and_interface_names(monkeypatch):
    monkeypatch.setenv("ROSLAB_SANDBOX", "roslab-e2e")
    e2e = Instance.from_env()
    default = Instance.from_env("roslab")
    assert not e2e.subnet.overlaps(default.subnet)
    assert e2e.subnet.subnet_of(ipaddress.IPv4Network("10.213.0.0/16"))
    assert e2e.bridge != default.bridge
    host = e2e.plan_hosts(40)[-1]
    for name in (e2e.bridge, e2e.veth(host)):
        assert len(name) <= 15, name  # the kernel's limit for interface names


def test_subnet_can_be_chosen(monkeypatch):
    monkeypatch.setenv("ROSLAB_SANDBOX_SUBNET", "10.99.7.0/24")
    assert Instance.from_env("mine").bridge_address == "10.99.7.1"


@pytest.mark.parametrize("subnet, message", [
    ("10.99.7.0/28", "/24 or larger"),
    ("8.8.8.0/24", "private"),
    ("10.99.7.300/24", "not an IPv4 network"),
])
def test_bad_subnet_is_refused(monkeypatch, subnet, message):
    monkeypatch.setenv("ROSLAB_SANDBOX_SUBNET", subnet)
    with pytest.raises(SandboxError, match=message):
        Instance.from_env("mine")


@pytest.mark.parametrize("name", ["Roslab", "a b", "-x", "x" * 40, "roslab/../etc"])
def test_bad_instance_name_is_refused(name):
    with pytest.raises(SandboxError, match="sandbox name"):
        Instance.from_env(name)


def test_derived_subnets_are_stable():
    assert default_subnet("roslab-e2e") == default_subnet("roslab-e2e")
    assert default_subnet("roslab-e2e") != default_subnet("roslab-net")


# -- the classroom ---------------------------------------------------------------------------

def test_default_classroom_is_two_teams_on_two_releases():
    hosts = Instance.from_env().plan_hosts(lifecycle.DEFAULT_HOSTS)
    assert [(h.name, h.role, h.release, h.address) for h in hosts] == [
        ("team1-main", "main", "24.04", "10.213.0.11"),
        ("team1-robot", "robot", "24.04", "10.213.0.12"),
        ("team2-main", "main", "22.04", "10.213.0.13"),
        ("team2-robot", "robot", "22.04", "10.213.0.14"),
    ]


def test_odd_host_count_leaves_the_last_team_with_a_main_only():
    hosts = Instance.from_env().plan_hosts(5)
    assert [h.name for h in hosts][-1] == "team3-main"
    assert hosts[-1].release == "24.04"


@pytest.mark.parametrize("count", [0, 201])
def test_host_count_out_of_range_is_refused(count):
    with pytest.raises(SandboxError, match="1 to 200 hosts"):
        Instance.from_env().plan_hosts(count)


def _published() -> upstream.Upstream:
    return upstream.Upstream(url=URL, ros_apt_source_sha256={"noble": "a" * 64, "jammy": "b" * 64})


def test_written_roster_is_a_valid_roster(tmp_path):
    instance = Instance.from_env()
    classroom = lifecycle.Classroom(instance, instance.plan_hosts(4))
    path = tmp_path / "roster.yaml"
    written = lifecycle.roster(classroom, _published())
    path.write_text(yaml.safe_dump(written))
    # The key exists once `up` made it; here a stand-in file passes the roster's check.
    key = tmp_path / "id_ed25519"
    key.write_text("-----BEGIN OPENSSH PRIVATE KEY-----\nstand-in key\n-----END OPENSSH PRIVATE KEY-----\n")
    loadable = tmp_path / "loadable.yaml"
    loadable.write_text(yaml.safe_dump({**written, "classroom": {**written["classroom"], "ssh_key": str(key)}}))

    loaded = load_roster(loadable)

    groups = inventory_groups(loaded)
    assert sorted(name for name, _ in groups["main"]) == ["team1-main", "team2-main"]
    data = yaml.safe_load(path.read_text())
    # Strict host key checking through roslab's known_hosts beside the sandbox roster,
    # named explicitly so a copy of the roster elsewhere checks against the same file.
    assert data["classroom"]["ssh_strict_host_key_checking"] == "yes"
    assert data["classroom"]["ssh_known_hosts_file"] == "/run/roslab/sandbox/roslab/.roslab-state/known_hosts"
    assert data["classroom"]["ssh_key"] == "/run/roslab/sandbox/roslab/id_ed25519"
    assert data["classroom"]["ros_apt_source_url"].format(version="1.2.0", codename="noble") == (
        f"{URL}/ros-apt-source/1.2.0/ros2-apt-source_1.2.0.noble_all.deb")
    assert data["teams"]["team2"]["ubuntu_release"] == "22.04"
    assert data["teams"]["team2"]["ros_domain_id"] == 12


# -- Ubuntu emulation --------------------------------------------------------------------------

def _identity(release: str) -> emulation.HostIdentity:
    return emulation.HostIdentity(hostname="team1-main", release=release, address="10.213.0.11", prefixlen=24)


def _parse_os_release(text: str) -> dict:
    pairs = (line.split("=", 1) for line in text.splitlines() if "=" in line and not line.startswith("#"))
    return {key: value.strip('"') for key, value in pairs}


@pytest.mark.parametrize("release, codename", [("24.04", "noble"), ("22.04", "jammy")])
def test_os_release_reads_as_ubuntu_and_says_it_is_emulated(release, codename):
    text = emulation.os_release(_identity(release))
    fields = _parse_os_release(text)
    assert (fields["ID"], fields["VERSION_ID"], fields["VERSION_CODENAME"], fields["UBUNTU_CODENAME"]) == (
        "ubuntu", release, codename, codename)
    assert text.startswith("# roslab sandbox emulation")


def test_noble_sources_are_deb822_without_universe_or_updates():
    path, text = emulation.apt_sources(_identity("24.04"), f"{URL}/ubuntu")
    assert path == "/etc/apt/sources.list.d/ubuntu.sources"
    assert "Suites: noble noble-security\n" in text
    assert "Components: main restricted\n" in text
    assert f"Signed-By: {emulation.UBUNTU_KEYRING}\n" in text


def test_jammy_sources_are_one_line_without_universe():
    path, text = emulation.apt_sources(_identity("22.04"), f"{URL}/ubuntu")
    assert path == "/etc/apt/sources.list"
    lines = [line for line in text.splitlines() if not line.startswith("#")]
    assert lines == [f"deb {URL}/ubuntu jammy main restricted", f"deb {URL}/ubuntu jammy-security main restricted"]


def test_netplan_file_is_a_valid_networkd_static_config():
    files = emulation.host_files(_identity("24.04"), f"{URL}/ubuntu")
    content, mode = files["/etc/netplan/50-cloud-init.yaml"]
    assert mode == 0o600
    assert "cloud-init" in content.splitlines()[0]
    network = yaml.safe_load(content)["network"]
    assert network["renderer"] == "networkd"
    assert network["ethernets"]["eth0"]["addresses"] == ["10.213.0.11/24"]


# -- the machine's Debian sources -----------------------------------------------------------------

def test_image_is_built_from_the_machines_debian_sources_only(tmp_path):
    (tmp_path / "sources.list.d").mkdir()
    (tmp_path / "sources.list.d/debian.sources").write_text(textwrap.dedent("""\
        Types: deb
        URIs: http://mirror.example/debian
        Suites: bookworm bookworm-updates
        Components: main
        Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

        Types: deb
        URIs: https://thirdparty.example/apt
        Suites: nodistro
        Components: main
        """))
    (tmp_path / "sources.list").write_text(
        "deb [signed-by=/k.gpg] http://security.example/debian-security bookworm-security main\n"
        "deb https://packages.cloud.example/apt cloud-sdk-bookworm main\n"
    )
    text = image.debian_sources(tmp_path, codename="bookworm")
    assert "mirror.example/debian\nSuites: bookworm bookworm-updates\n" in text
    assert "URIs: http://security.example/debian-security\nSuites: bookworm-security\n" in text
    assert "Signed-By: /k.gpg" in text
    assert "thirdparty" not in text and "cloud" not in text


def test_no_debian_sources_is_a_clear_error(tmp_path):
    with pytest.raises(SandboxError, match="no Debian bookworm sources"):
        image.debian_sources(tmp_path, codename="bookworm")


# -- upstream data ---------------------------------------------------------------------------------

def test_node_dependencies_split_ros_and_system_keys_and_skip_own_packages(tmp_path):
    for name, deps in {"demo": ["rclpy", "python3-pytest", "ament_flake8"], "bringup": ["demo", "launch_ros"]}.items():
        (tmp_path / name).mkdir()
        depends = "".join(f"<exec_depend>{dep}</exec_depend>" for dep in deps)
        (tmp_path / name / "package.xml").write_text(
            f'<?xml version="1.0"?><package format="3"><name>{name}</name>{depends}</package>')
    ros_keys, system = upstream.node_dependencies(tmp_path)
    assert ros_keys == {"rclpy", "ament_flake8", "launch_ros"}
    assert system == {"python3-pytest": "python3-pytest"}


def test_repository_nodes_need_only_stand_ins_the_archive_has():
    ros_keys, system = upstream.node_dependencies(upstream.default_nodes_dir())
    assert ros_keys <= set(upstream.ros_keys_for(ros_keys))
    assert set(system.values()) <= set(upstream.universe_packages({**upstream.SYSTEM_ROSDEP_KEYS, **system}))


def test_rosdistro_index_resolves_ros_keys_to_stand_in_packages(tmp_path):
    files = upstream.rosdistro_files(URL, upstream.ros_keys_for(set()))
    for path, content in files.items():
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(content)
    # rosdep reads the index with the rosdistro library, as done here.
    index = rosdistro.get_index((tmp_path / "rosdistro/index-v4.yaml").as_uri())
    assert sorted(index.distributions) == ["humble", "jazzy", "lyrical"]
    jazzy = rosdistro.get_distribution_file(index, "jazzy")
    assert jazzy.release_platforms == {"ubuntu": ["noble"]}
    assert "rclpy" in jazzy.repositories
    assert upstream.debian_name("jazzy", "launch_ros") == "ros-jazzy-launch-ros"


def test_rosdep_sources_list_points_at_the_served_rules():
    files = upstream.rosdep_files(URL, {"python3-pytest": "python3-pytest", "git": "git"})
    lines = [line for line in files["rosdep/20-default.list"].splitlines() if not line.startswith("#")]
    assert lines == [f"yaml {URL}/rosdep/base.yaml", f"yaml {URL}/rosdep/python.yaml"]
    assert yaml.safe_load(files["rosdep/python.yaml"]) == {
        "python3-pytest": {"debian": ["python3-pytest"], "ubuntu": ["python3-pytest"]}}
    assert yaml.safe_load(files["rosdep/base.yaml"]) == {"git": {"debian": ["git"], "ubuntu": ["git"]}}


def test_stand_in_setup_script_sets_the_ros_environment_once(tmp_path):
    script = tmp_path / "setup.bash"
    script.write_text(upstream.setup_script("jazzy"))
    out = subprocess.run(
        ["bash", "-c", f". {script}; . {script}; echo $ROS_DISTRO $ROS_VERSION $ROS_PYTHON_VERSION $AMENT_PREFIX_PATH"],
        capture_output=True, text=True, check=True, env={"PATH": "/usr/bin:/bin"},
    ).stdout.split()
    assert out == ["jazzy", "2", "3", "/opt/ros/jazzy"]


def test_ros2_sources_is_deb822_with_its_key_inline_as_the_real_one():
    armored = "-----BEGIN PGP PUBLIC KEY BLOCK-----\n\nmQINBGtest\nabc=\n-----END PGP PUBLIC KEY BLOCK-----\n"
    text = upstream.ros2_sources(URL, "jammy", armored)
    assert f"URIs: {URL}/ros2/ubuntu\n" in text
    assert "Suites: jammy\n" in text
    assert text.endswith("Signed-By: -----BEGIN PGP PUBLIC KEY BLOCK-----\n .\n mQINBGtest\n abc=\n"
                         " -----END PGP PUBLIC KEY BLOCK-----\n")
    # apt reads it: one stanza whose Signed-By field holds the whole block
    import email.parser
    fields = email.parser.Parser().parsestr("\n".join(line for line in text.splitlines() if not line.startswith("#")))
    assert fields["Signed-By"].split()[:5] == ["-----BEGIN", "PGP", "PUBLIC", "KEY", "BLOCK-----"]


def test_mirror_settings_name_the_mirror_and_the_key_file(tmp_path):
    settings = _published().mirror_settings(tmp_path / "ros.asc")
    assert settings == {"ros_apt_mirror_url": f"{URL}/ros2/ubuntu", "ros_apt_mirror_key_file": str(tmp_path / "ros.asc")}


def test_roster_settings_are_known_deploy_settings():
    import deploy

    assert set(_published().roster_settings()) <= set(settings.SETTINGS)
    assert set(_published().mirror_settings(Path("/k"))) <= set(settings.SETTINGS)


def test_ros_apt_source_stand_in_installs_key_and_linked_source(tmp_path, monkeypatch):
    import hashlib

    monkeypatch.setenv("ROSLAB_CACHE_DIR", str(tmp_path / "cache"))  # a throwaway signing key
    sums = upstream.build_ros_apt_source(tmp_path / "serve", URL)

    deb = tmp_path / "serve/ros-apt-source/1.2.0/ros2-apt-source_1.2.0.noble_all.deb"
    assert sums["noble"] == hashlib.sha256(deb.read_bytes()).hexdigest()
    listing = subprocess.run(["dpkg-deb", "--contents", deb], capture_output=True, text=True, check=True).stdout
    assert "./usr/share/keyrings/ros2-archive-keyring.gpg" in listing
    assert "./usr/share/ros-apt-source/ros2.sources" in listing
    assert "./etc/apt/sources.list.d/ros2.sources -> /usr/share/ros-apt-source/ros2.sources" in listing
    assert all(" root/root " in line for line in listing.splitlines())
    fields = subprocess.run(["dpkg-deb", "--field", deb, "Package", "Version", "Description"],
                            capture_output=True, text=True, check=True).stdout
    assert "Package: ros2-apt-source\nVersion: 1.2.0\n" in fields
    assert "roslab sandbox stand-in" in fields


def test_desktop_hosts_get_networkmanager_netplan_instead_of_cloud_init():
    hosts = Instance.from_env().plan_hosts(4, desktop=["team1-main"])
    assert [h.flavour for h in hosts] == ["desktop", "server", "server", "server"]
    files = emulation.host_files(hosts[0].identity(24), f"{URL}/ubuntu")
    assert "/etc/netplan/50-cloud-init.yaml" not in files
    network = yaml.safe_load(files["/etc/netplan/01-network-manager-all.yaml"][0])["network"]
    assert network["renderer"] == "NetworkManager"
    assert network["ethernets"]["eth0"]["addresses"] == ["10.213.0.11/24"]


def test_unknown_desktop_host_is_refused():
    with pytest.raises(SandboxError, match="--desktop team9-main: no such host"):
        Instance.from_env().plan_hosts(4, desktop=["team9-main"])


# -- host keys, re-flashing and seeded boots -------------------------------------------------------

def test_ssh_checks_host_keys_strictly_against_the_sandbox_known_hosts():
    instance = Instance.from_env()
    argv = lifecycle.ssh_argv(instance, "10.213.0.11", "true")
    options = [argv[i + 1] for i, word in enumerate(argv) if word == "-o"]
    assert "StrictHostKeyChecking=yes" in options
    assert "UserKnownHostsFile=/run/roslab/sandbox/roslab/.roslab-state/known_hosts" in options
    assert not any(option.startswith("HostKeyAlias") for option in options)
    # By name, a host that moved to another address is still recognised by its key.
    moved = lifecycle.ssh_argv(instance, "10.213.0.111", "true", host_name="team1-main")
    assert "HostKeyAlias=team1-main" in moved and moved[-2:] == ["ubuntu@10.213.0.111", "true"]


@pytest.mark.parametrize("flashes, expected", [
    ([{}], {"seeded": True, "seed": None}),  # made by `up`: keeps its key from the store
    ([{"unseeded": True}], {"seeded": False, "seed": None}),
    ([{"unseeded": True}, {}], {"seeded": False, "seed": None}),  # stays unseeded: a new key each time
    ([{"seed_copy": Path("/s")}], {"seeded": True, "seed": "/s"}),
    ([{"seed_copy": Path("/s")}, {}], {"seeded": True, "seed": "/s"}),  # the same card again
    ([{"seed_copy": Path("/s")}, {"unseeded": True}], {"seeded": False, "seed": None}),
])
def test_a_reflash_keeps_the_host_seeded_only_as_asked(flashes, expected):
    state = {"seeded": True}  # what `up` records
    for flash in flashes:
        state = lifecycle.reflash_state(state, **flash)
    assert {key: state[key] for key in expected} == expected
    assert state["apt_lock_seconds"] == seeding.FIRST_BOOT_APT_LOCK_SECONDS
    assert lifecycle.reflash_state(state, apt_lock_seconds=3)["apt_lock_seconds"] == 3


@pytest.fixture
def host_root(tmp_path, monkeypatch):
    """A host's root (with the base image's cloud-init files) and what `systemctl --root` was asked."""
    root = tmp_path / "root"
    for path, content in seeding.cloud_init_image_files().items():
        (root / path.lstrip("/")).parent.mkdir(parents=True, exist_ok=True)
        (root / path.lstrip("/")).write_text(content)
    (root / seeding.CLOUD_INIT_DISABLED.lstrip("/")).write_text(seeding.CLOUD_INIT_DISABLED_TEXT)
    (root / "home/ubuntu").mkdir(parents=True)
    (root / "etc/ssh").mkdir(parents=True)
    (root / "etc/ssh/ssh_host_ed25519_key").write_text("from an earlier boot\n")
    calls = []
    monkeypatch.setattr(hosts, "run", lambda *argv, **kwargs: calls.append([str(arg) for arg in argv]))
    monkeypatch.setattr(hosts.os, "chown", lambda *args: None)
    instance = Instance("unit", ipaddress.IPv4Network("10.213.99.0/24"))
    monkeypatch.setattr(Instance, "state_dir", property(lambda self: tmp_path / "state"))
    instance.key_path.parent.mkdir(parents=True)
    instance.key_path.with_suffix(".pub").write_text("ssh-ed25519 AAAAlogin login\n")
    return instance, instance.plan_hosts(2)[0], root, calls


def test_a_host_booted_with_a_key_gets_that_key_and_keeps_cloud_init_disabled(host_root):
    instance, host, root, _ = host_root
    boot = hosts.Boot(host_key=("PRIVATE\n", "ssh-ed25519 AAAAhost root@team1-main"))
    hosts.write_host_files(instance, host, root, b"keyring", boot)
    assert (root / "etc/ssh/ssh_host_ed25519_key").read_text() == "PRIVATE\n"
    assert (root / "etc/ssh/ssh_host_ed25519_key").stat().st_mode & 0o777 == 0o600
    assert (root / "etc/ssh/ssh_host_ed25519_key.pub").read_text() == "ssh-ed25519 AAAAhost root@team1-main\n"
    assert (root / seeding.CLOUD_INIT_DISABLED.lstrip("/")).exists()
    assert (root / "etc/netplan/50-cloud-init.yaml").exists()
    assert (root / "etc/hostname").read_text() == "team1-main\n"
    assert (root / "home/ubuntu/.ssh/authorized_keys").read_text() == "ssh-ed25519 AAAAlogin login\n"


def test_a_host_booted_from_a_seed_gets_cloud_init_and_nothing_the_seed_brings(host_root):
    instance, host, root, calls = host_root
    hosts.write_host_files(instance, host, root, b"keyring", hosts.Boot(seed=Path("/seed"), apt_lock_seconds=7))
    # cloud-init runs, finds the boot partition's files where NoCloud reads them (with network-config).
    assert not (root / seeding.CLOUD_INIT_DISABLED.lstrip("/")).exists()
    assert (root / "var/lib/cloud/seed/nocloud").readlink() == Path("/boot/firmware")
    datasource = yaml.safe_load((root / "etc/cloud/cloud.cfg.d/99-fake_cloud.cfg").read_text())
    assert datasource == {"datasource_list": ["NoCloud", "None"],
                          "datasource": {"NoCloud": {"fs_label": "system-boot"}}}
    # What the seed brings is left to cloud-init: host key, user's key, hostname, network.
    assert not list((root / "etc/ssh").glob("ssh_host_*"))
    assert not (root / "home/ubuntu/.ssh/authorized_keys").exists()
    assert not (root / "etc/netplan/50-cloud-init.yaml").exists()
    assert (root / "etc/hostname").read_text() == "ubuntu\n"
    # The Ubuntu emulation stays.
    assert "ID=ubuntu" in (root / "usr/lib/os-release").read_text()
    # The first-boot unattended-upgrades stand-in, named as one, holding the lock 7 s.
    unit = (root / "etc/systemd/system" / seeding.FIRST_BOOT_UNIT).read_text()
    assert "STAND-IN for Ubuntu's first-boot unattended-upgrades" in unit
    assert "STAND-IN" in (root / seeding.FIRST_BOOT_SCRIPT.lstrip("/")).read_text()
    assert "HOLD_SECONDS=7\n" in (root / seeding.FIRST_BOOT_CONFIG.lstrip("/")).read_text()
    assert ["systemctl", f"--root={root}", "enable", "--quiet", seeding.FIRST_BOOT_UNIT] in calls


def test_no_lock_stand_in_when_asked_for_zero_seconds(host_root):
    instance, host, root, calls = host_root
    hosts.write_host_files(instance, host, root, b"keyring", hosts.Boot(seed=Path("/seed"), apt_lock_seconds=0))
    assert not (root / "etc/systemd/system" / seeding.FIRST_BOOT_UNIT).exists()
    assert not calls


def test_the_seed_is_bound_read_only_as_the_boot_partition(tmp_path):
    instance = Instance.from_env()
    host = instance.plan_hosts(1)[0]
    plain = hosts.nspawn_argv(instance, host, tmp_path)
    seeded = hosts.nspawn_argv(instance, host, tmp_path, seed=tmp_path / "seed")
    assert seeded[:len(plain)] == plain
    assert seeded[len(plain):] == [f"--bind-ro={tmp_path / 'seed'}:/boot/firmware"]


def test_every_host_compiles_into_the_machines_one_compile_cache(tmp_path, monkeypatch):
    """Bound read-write where the image's ccache.conf and compiler links point, from a folder only
    root can reach on the machine (the cache itself is writable by every host user)."""
    monkeypatch.setenv("ROSLAB_CACHE_DIR", str(tmp_path / "cache"))
    instance = Instance.from_env()
    argv = hosts.nspawn_argv(instance, instance.plan_hosts(1)[0], tmp_path)
    assert f"--bind={tmp_path / 'cache/ccache/cache'}:{image.COMPILE_CACHE}" in argv
    shared = image.ensure_compile_cache()
    assert shared == tmp_path / "cache/ccache/cache"
    assert stat.S_IMODE(shared.parent.stat().st_mode) == 0o700 and stat.S_IMODE(shared.stat().st_mode) == 0o777
    assert f"cache_dir = {image.COMPILE_CACHE}\n" in image.COMPILE_CACHE_CONF and "ccache" in image.BASE_PACKAGES


def test_the_stand_in_script_is_valid_python_that_locks_as_apt_does():
    compile(seeding.FIRST_BOOT_SCRIPT_TEXT, seeding.FIRST_BOOT_SCRIPT, "exec")
    text = seeding.FIRST_BOOT_SCRIPT_TEXT
    assert text.index("/var/lib/dpkg/lock-frontend") < text.index('"/var/lib/dpkg/lock"')  # apt's order
    assert "fcntl.lockf(handle, fcntl.LOCK_EX)" in text


SUBNET = ipaddress.IPv4Network("10.213.41.0/24")
STATIC = "network:\n  version: 2\n  ethernets:\n    eth0:\n      addresses: [10.213.41.12/24]\n"


@pytest.mark.parametrize("files, message", [
    (None, "not a directory"),
    ({"meta-data": ""}, "no user-data"),
    ({"user-data": "", "network-config": STATIC}, "no meta-data"),
    # No DHCP server on the sandbox network: a seed without a static address would never answer.
    ({"user-data": "", "meta-data": ""}, "no static address in the sandbox's subnet 10.213.41.0/24 .*DHCP only"),
    ({"user-data": "", "meta-data": "", "network-config": "network: {version: 2, ethernets: {eth0: {dhcp4: true}}}"},
     "DHCP only.*network_address"),
    ({"user-data": "", "meta-data": "", "network-config": STATIC.replace("10.213.41.", "192.168.50.")},
     "it has 192.168.50.12"),
])
def test_a_folder_that_is_not_a_usable_seed_is_refused(tmp_path, files, message):
    seed = tmp_path / "seed"
    if files is not None:
        seed.mkdir()
        for name, text in files.items():
            (seed / name).write_text(text)
    with pytest.raises(SandboxError, match=message):
        seeding.seed_address(seed, SUBNET)


def test_a_seed_gives_its_static_address(tmp_path):
    for name, text in {"user-data": "#cloud-config\n", "meta-data": "", "network-config": STATIC}.items():
        (tmp_path / name).write_text(text)
    assert seeding.seed_address(tmp_path, SUBNET) == "10.213.41.12"


@pytest.mark.parametrize("user_data, enabled", [
    ("#cloud-config\nlocale: de_DE.UTF-8\n", "de_DE.UTF-8 UTF-8\n"),
    ("#cloud-config\nhostname: x\n", None),  # no locale: nothing to emulate
    ("#cloud-config\nlocale: 'x; rm -rf /'\n", None),  # not a locale name
])
def test_the_seeds_locale_is_enabled_as_ubuntus_locale_gen_would_generate_it(user_data, enabled):
    locale_gen = "# en_US.UTF-8 UTF-8\n# de_DE.UTF-8 UTF-8\n"
    result = seeding.seed_locale_enabled(locale_gen, user_data)
    if enabled is None:
        assert result == locale_gen
    else:
        assert enabled in result.splitlines(keepends=True)
        assert "# en_US.UTF-8 UTF-8\n" in result


def test_a_kept_seed_is_root_only(tmp_path, monkeypatch):
    monkeypatch.setattr(Instance, "state_dir", property(lambda self: tmp_path / "state"))
    instance = Instance.from_env()
    host = instance.plan_hosts(1)[0]
    seed = tmp_path / "seed"
    seed.mkdir()
    for name in ("user-data", "meta-data", "network-config", "README"):
        (seed / name).write_text(name)
    copy = hosts.keep_seed(instance, host, seed)
    assert sorted(path.name for path in copy.iterdir()) == ["meta-data", "network-config", "user-data"]
    assert copy.stat().st_mode & 0o777 == 0o700
    assert {path.stat().st_mode & 0o777 for path in copy.iterdir()} == {0o600}
    assert hosts.keep_seed(instance, host, copy) == copy  # booting from the kept copy again


def test_an_lxcfs_mount_left_by_a_killed_run_is_not_taken_for_a_running_lxcfs(monkeypatch):
    # A killed lxcfs leaves its FUSE mount: every stat under it fails with ENOTCONN.
    class DeadMount:
        def __truediv__(self, other):
            return self

        def exists(self):
            raise OSError(errno.ENOTCONN, "Transport endpoint is not connected")

        def is_mount(self):
            raise OSError(errno.ENOTCONN, "Transport endpoint is not connected")

    unmounted = []
    monkeypatch.setattr(hosts, "LXCFS_DIR", DeadMount())
    monkeypatch.setattr(hosts, "run", lambda *argv, **kwargs: unmounted.append(argv))
    assert hosts.lxcfs_running() is False
    hosts._unmount_stale_lxcfs()
    assert unmounted and unmounted[0][:2] == ("umount", "--lazy")


def test_a_long_sandbox_step_says_what_it_does_while_it_lasts_and_when_it_is_done(caplog):
    import logging
    import time as _time

    from roslab.sandbox.system import announced

    with caplog.at_level(logging.INFO, logger="roslab.sandbox"):
        with announced("building the thing", every=0.1):
            _time.sleep(0.35)
    messages = [record.getMessage() for record in caplog.records]
    assert messages[0] == "building the thing ..."
    assert any(message.startswith("  still building the thing (") for message in messages[1:-1])
    assert messages[-1].startswith("building the thing: done in ")


def test_a_class_on_a_real_runtime_runs_cyclone_dds_which_both_runtimes_have():
    real = upstream.Upstream(url=URL, ros_apt_source_sha256={}, ros={
        "jazzy": "real (ros-jazzy-core-debian12-amd64.tar.zst, sha256 bd465e21560d)", "humble": "stand-in"})
    assert real.roster_settings()["ros_middleware"] == "rmw_cyclonedds_cpp"
    stand_ins = upstream.Upstream(url=URL, ros_apt_source_sha256={}, ros={"jazzy": "stand-in"})
    assert "ros_middleware" not in stand_ins.roster_settings()  # roslab's default, Fast DDS


def test_a_signing_key_is_made_and_signs_in_a_cache_folder_too_deep_for_gpgs_agent_socket(tmp_path, monkeypatch):
    """gpg's agent socket lives in its home, and a socket path has at most 107 bytes: a deep
    ROSLAB_CACHE_DIR (a test worker's temporary folder) must still get its key and signatures."""
    deep = tmp_path / ("a-folder-deep-enough-for-the-socket-path-limit-" * 3) / "cache"
    assert len(str(deep / "keys" / "ros" / "S.gpg-agent")) > 107
    monkeypatch.setenv("ROSLAB_CACHE_DIR", str(deep))
    key = upstream.ros_key()
    release = tmp_path / "Release"
    release.write_text("Origin: stand-in\n")
    key.sign_release(release)
    assert key.keyring.stat().st_size > 0 and len(key.fingerprint) == 40
    assert "BEGIN PGP SIGNED MESSAGE" in (tmp_path / "InRelease").read_text()


def test_a_cards_first_boot_is_a_flashed_hosts_and_a_later_boot_finds_the_disk_as_it_was_left(host_root):
    """A card of the sandbox's own image (card.py) is the host's disk: on its first boot it gets
    what any host booted from a seed gets; once its cloud-init has an instance (an absolute
    symlink into the card), the sandbox writes nothing on it: not the host key's removal, not
    the apt layout a deploy may have changed, not a new machine id."""
    instance, host, root, calls = host_root
    boot = hosts.Boot(seed=Path("/seed"), apt_lock_seconds=0, card=Path("/dev/loop9"))
    hosts.write_host_files(instance, host, root, b"keyring", boot)
    assert not list((root / "etc/ssh").glob("ssh_host_*"))  # first boot: as flashed
    assert "ID=ubuntu" in (root / "usr/lib/os-release").read_text()
    (root / "etc/ssh/ssh_host_ed25519_key").write_text("made by its first boot\n")
    (root / "var/lib/cloud").mkdir(parents=True, exist_ok=True)
    (root / "var/lib/cloud/instance").symlink_to("/var/lib/cloud/instances/iid-team1-robot")
    (root / "etc/machine-id").write_text("0123\n")
    (root / "usr/lib/os-release").write_text("as the deploy left it\n")
    calls.clear()
    hosts.write_host_files(instance, host, root, b"keyring", boot)
    assert (root / "etc/ssh/ssh_host_ed25519_key").read_text() == "made by its first boot\n"
    assert (root / "etc/machine-id").read_text() == "0123\n"
    assert (root / "usr/lib/os-release").read_text() == "as the deploy left it\n"
    assert not calls


def test_a_cards_system_boot_is_bound_read_write_as_a_pi_mounts_it(tmp_path):
    instance = Instance.from_env()
    host = instance.plan_hosts(1)[0]
    plain = hosts.nspawn_argv(instance, host, tmp_path)
    on_card = hosts.nspawn_argv(instance, host, tmp_path, seed=tmp_path / "boot", card=True)
    assert on_card[len(plain):] == [f"--bind={tmp_path / 'boot'}:/boot/firmware"]


def test_a_host_runs_on_its_card_only_while_reflashes_name_it():
    state = lifecycle.reflash_state({"seeded": True}, seed_copy=Path("/s"), card=Path("/dev/loop9"))
    assert (state["seeded"], state["seed"], state["card"]) == (True, "/s", "/dev/loop9")
    # A plain reset lets the card go: the sandbox's image, with the card's seed.
    state = lifecycle.reflash_state(state)
    assert (state["seeded"], state["seed"], state["card"]) == (True, "/s", None)


def test_up_prints_the_deploy_and_the_verify_command_for_its_own_roster(capsys):
    """A teacher with a classroom folder needs the sandbox's roster for verify and status too: in
    the folder, a bare `roslab verify` would read classroom.yaml, the real Pis' addresses."""
    from roslab.sandbox.cli import print_status

    roster = "/run/roslab/sandbox/trial/roster.yaml"
    print_status({"name": "trial", "subnet": "10.213.178.0/24", "upstream": "http://10.213.178.1:8080",
                  "roster": roster, "hosts": []})
    out = capsys.readouterr().out.splitlines()
    assert f"       or: ROSLAB_ROSTER={roster} pyinfra -y inventory.py deploy.py   (in a `roslab init` folder)" in out
    assert f"check it: roslab verify {roster}   (and roslab status, roslab check: the same roster)" in out
