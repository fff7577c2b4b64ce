"""The settings schema: every roster setting declared once, grouped by concern.

Each `Setting` has its default, its type (with the element type of a list), the
format check its value must pass, and the doc line the settings table shows (docs/roster-and-settings.md). The
roster loader checks every value set at every level against it before any host is
touched, and merges the defaults into each host's data once; a deploy reads them typed,
through `roslab.host_settings.host_settings(host)` (the dataclass `roslab/host_fields.py`
generated from here), and its `data_defaults` are `defaults(concern)`.

    python -m roslab.settings_doc --write   # regenerate the docs' tables and host_fields.py
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from roslab.ros import discovery
from roslab.ros import distro as distros
from roslab import boards, openpgp, formats as f

# Where a key may be set: everywhere, or only at one level.
ANY = ("classroom", "team", "host")


@dataclass(frozen=True)
class Setting:
    key: str
    default: Any
    kind: type  # str, int, bool, list, dict
    doc: str
    concern: str  # the deploy (or "roster"/"connection") it belongs to
    check: f.Check | None = None  # format of the value (of each element, for a list)
    item: type | None = None  # element type of a list
    nullable: bool = False  # None is a legal value (the default says what None means)
    levels: tuple[str, ...] = ANY
    required: bool = False
    allowed: str = ""  # the allowed values in words, for the settings table

    def allowed_text(self) -> str:
        if self.allowed:
            return self.allowed
        if self.kind is bool:
            return "true, false"
        choices = getattr(self.check, "choices", None)
        if choices:
            return ", ".join(str(choice) for choice in choices)
        described = getattr(self.check, "allowed", None)
        if described:
            return described
        doc = (self.check.__doc__ or "").strip().splitlines() if self.check else []
        return doc[0] if doc else ""

    def type_text(self) -> str:
        name = {str: "string", int: "integer", bool: "boolean", list: "list", dict: "mapping"}[self.kind]
        if self.item is not None:
            name += f" of {({str: 'strings', int: 'integers'})[self.item]}"
        return name + (" or null" if self.nullable else "")


def _s(key, default, kind, doc, check=None, **more) -> Setting:
    return Setting(key, default, kind, doc, more.pop("concern"), check, **more)


def _concern(name: str, *settings: tuple) -> list[Setting]:
    return [_s(*spec[:5], concern=name, **(spec[5] if len(spec) > 5 else {})) for spec in settings]


def _enabled(concern: str, doc: str) -> tuple:
    return (f"{concern}_enabled", True, bool, doc)


def _repos_file(value, context=None):
    """A .repos file (vcstool's format), relative to the roster, inside its folder."""
    from roslab.sources.repos import repos_file_problem  # it reads YAML with the roster's loader

    return repos_file_problem(value, context)


def _url_rewrites(value, context=None):
    """URL prefix -> replacement prefix (http, https, file), as git's insteadOf."""
    from roslab.sources.repos import rewrites_problem

    return rewrites_problem(value, context)


def _source_pins(value, context=None):
    """Repository path -> a commit or a tag."""
    from roslab.sources.repos import pins_problem

    return pins_problem(value, context)


f.describe(_repos_file, allowed="a .repos file, relative to the roster")
f.describe(_source_pins, allowed="repository path: commit (40 hex) or tag")
f.describe(_url_rewrites, allowed="URL prefix: replacement prefix (http, https, file:// in the roster's folder)")

SECONDS_PER_DAY = 24 * 3600
SCHEMA: list[Setting] = [
    # --- the roster's own keys (identity and connection) ---
    *_concern(
        "roster",
        ("name", None, str, "The classroom's name (shown by roslab check).", f.single_line,
         {"nullable": True, "levels": ("classroom",)}),
        ("secrets_file", "secrets.yaml", str,
         "Where secrets are read from, relative to the roster (mode 0600, never committed): a .yaml "
         "file in the roster's folder or a folder below it (not .roslab-state), where it really is "
         "(symlinks followed; the default too).",
         f.secrets_file, {"levels": ("classroom",)}),
        ("role", None, str, "main (runs the desktop variant and the main launch) or robot.",
         f.choice("main", "robot"), {"levels": ("host",), "required": True}),
        ("address", None, str,
         "Where SSH reaches the host now (IP or DNS name; not an unspecified, multicast, broadcast or "
         "reserved address); default: the host name.",
         f.address, {"levels": ("host",), "nullable": True}),
    ),
    *_concern(
        "connection",
        ("ssh_user", "ubuntu", str, "SSH login user, also the user who gets the ROS environment.",
         f.linux_user),
        ("ssh_port", 22, int, "SSH port.", f.int_range(1, 65535)),
        ("ssh_key", None, str,
         "Private key file on this machine (relative to the roster): an SSH private key "
         "(-----BEGIN ... PRIVATE KEY-----), a regular file of at most 64 KiB.",
         f.private_key_file, {"nullable": True}),
        ("ssh_known_hosts_file", None, str,
         "known_hosts file pyinfra checks host keys against; None: the classroom's own, "
         "`.roslab-state/known_hosts` beside the roster (`roslab seed`, `roslab trust`, `roslab forget` "
         "use the same file). Its name must end in known_hosts and it may hold only host key lines "
         "(pyinfra appends to it); /dev/null records nothing.",
         f.known_hosts_file, {"nullable": True}),
        ("ssh_strict_host_key_checking", None, str,
         "pyinfra's host key policy; None: yes (a host whose key is not recorded, or changed, is refused "
         "with the roslab command to run).",
         f.choice("yes", "no", "off", "ask", "accept-new"), {"nullable": True}),
        ("sudo_password_secret", None, str, "Name of a secret holding the sudo password.",
         f.secret_name, {"nullable": True}),
        ("console_password_secret", None, str,
         "Name of a secret holding a password for the lab user at the Pi's own console (keyboard "
         "and screen), the way in when its network is wrong; None: no password at all. Put in the "
         "seed hashed (SHA-512 crypt), never in plain text; SSH password login stays off.",
         f.secret_name, {"nullable": True}),
    ),
    # --- deploy settings ---
    *_concern(
        "common",
        ("login_user", None, str,
         "The user who owns the ROS environment (~/.bashrc, ~/ros2_ws, the rosdep cache); "
         "None: the SSH user.", f.linux_user, {"nullable": True}),
        ("offline", False, bool,
         "Provision without the internet: the controller uses only its own cache (the ros2-apt-source "
         ".deb, rosdep's data), the apt cache serves only what it holds, and no host downloads from "
         "upstream directly.", None, {"levels": ("classroom",)}),
        ("run_lock_wait", 600, int,
         "Seconds a run waits for another roslab run on the same host (a second teacher, a cron run) "
         "to end before it stops that host; the line names the other run's controller, user, pid and "
         "start time. The lock is held for the other run's SSH session only: a killed run never leaves it.",
         f.int_range(0, SECONDS_PER_DAY, " s")),
    ),
    *_concern(
        "apt_ready",
        _enabled("apt_ready", "Prepare apt: wait for the dpkg lock, enable universe and the "
                              "extra suites, refresh the lists."),
        ("apt_lock_timeout", 600, int,
         "Seconds to wait for the dpkg lock (first-boot unattended-upgrades holds it for minutes).",
         f.int_range(0, SECONDS_PER_DAY, " s")),
        ("apt_enable_universe", True, bool, "Enable the universe component (ROS 2 depends on packages there)."),
        ("apt_extra_suites", ["updates", "backports"], list,
         "Suites enabled beside the release, as suffixes: noble-updates, noble-backports. Without "
         "them ROS 2 on Pi server images fails with unmet dependencies.", f.apt_suite_suffix,
         {"item": str}),
        ("apt_cache_max_age", SECONDS_PER_DAY, int,
         "Seconds before the apt lists count as stale and `apt-get update` runs again.",
         f.int_range(0, 365 * SECONDS_PER_DAY, " s")),
    ),
    *_concern(
        "apt_cache",
        _enabled("apt_cache", "Use the classroom's apt cache (apt-cacher-ng on apt_cache_host): each .deb is "
                              "downloaded once for the class."),
        ("apt_cache_host", None, str,
         "The roster host that runs the apt cache (e.g. the teacher's machine or a main Pi); every "
         "host uses it as its apt proxy and falls back to direct downloads while it does not answer. "
         "None: no cache.", f.host_label, {"nullable": True, "levels": ("classroom",),
                                           "allowed": "a host in the roster"}),
        ("apt_cache_port", 3142, int, "The port the apt cache listens on.", f.int_range(1, 65535),
         {"levels": ("classroom",)}),
        ("apt_cache_upstream_ports", [80], list,
         "Ports the apt cache may download from (apt-cacher-ng allows 80 only): add a local "
         "mirror's port, e.g. 8080.", f.int_range(1, 65535), {"item": int, "levels": ("classroom",)}),
    ),
    *_concern(
        "locale",
        _enabled("locale", "Generate the locale and set it system-wide."),
        ("locale", "en_US.UTF-8", str,
         "The system-wide locale (LANG): a UTF-8 locale from glibc's supported list "
         "(roslab/data/locales-utf8.txt), like de_DE.UTF-8 or ca_ES.UTF-8@valencia.",
         f.utf8_locale),
        ("timezone", "Etc/UTC", str,
         "The time zone a Pi gets at first boot from its seed (`roslab seed`), like Europe/Berlin: "
         "a zone of the tz database (roslab/data/timezones.txt or the controller's own).",
         f.timezone),
    ),
    *_concern(
        "ros_apt_source",
        _enabled("ros_apt_source", "Configure the ROS 2 apt source (and move the old method's files aside)."),
        ("ros_apt_source_mode", "package", str,
         "package: install ros2-apt-source (official); mirror: a local mirror's key and URL; snapshot: "
         "the ROS archive as it was at one sync (snapshots.ros.org, LTS distros; ros_apt_snapshot).",
         f.choice("package", "mirror", "snapshot")),
        ("ros_apt_source_version", distros.ROS_APT_SOURCE_VERSION, str,
         f"The pinned ros2-apt-source release ({distros.ROS_APT_SOURCE_VERSION}, 2026-04).", f.version),
        ("ros_apt_source_sha256", distros.ros_apt_source_pins(), dict,
         "Ubuntu codename -> sha256 of that release's .deb (roslab/ros/distro.py's records). Pins set in a "
         "roster are added to these (for the default version; another version needs all its pins). "
         "resolute's is the one the official Docker images pin (osrf/docker_images); jammy's and noble's "
         "are copied from public install scripts. None is verified from here: check once online.",
         f.sha256_pins, {"allowed": "codename: 64 hex digits"}),
        ("ros_apt_source_url",
         "https://github.com/ros-infrastructure/ros-apt-source/releases/download/"
         "{version}/ros2-apt-source_{version}.{codename}_all.deb", str,
         "Where the controller downloads the .deb; {version} and {codename} are filled in. A "
         "file:// URL must name a .deb inside the roster's folder.",
         f.url(("http", "https", "file"), ("version", "codename"), file_suffix=".deb")),
        ("ros_apt_source_cache_dir", "~/.cache/roslab/ros-apt-source", str,
         "Download cache on the machine running pyinfra (not on the hosts): a folder of its own "
         "inside the home directory, the roster's folder or the temporary directory.", f.cache_dir),
        ("ros_apt_mirror_url", None, str,
         "Mirror mode: the mirror's URL (serving the ROS 2 archive's dists/ and pool/).", f.http_url,
         {"nullable": True}),
        ("ros_apt_mirror_key_file", None, str,
         "Mirror mode: path, on the machine running pyinfra, to the mirror's signing key "
         "(an OpenPGP public key, ASCII-armored or binary, at most 1 MiB; it is copied to every Pi).",
         f.openpgp_key_file, {"nullable": True}),
        ("ros_apt_snapshot", None, str,
         "Snapshot mode: the snapshot to install from, as snapshots.ros.org names them: a sync's date "
         "(YYYY-MM-DD) or final (a distro's last, after its end of life). New installs get that sync's "
         "versions; a class lock keeps them.", f.ros_snapshot, {"nullable": True}),
        ("ros_apt_snapshot_url", "http://snapshots.ros.org", str,
         "Snapshot mode: the snapshot server (a local mirror of it may stand in); a host's source is "
         "<this>/<distro>/<snapshot>/ubuntu.", f.http_url),
        ("ros_apt_snapshot_key_file", None, str,
         "Snapshot mode: path, on the machine running pyinfra, to the snapshot repository's signing key "
         "(not packages.ros.org's); from snapshots.ros.org its fingerprint must be "
         f"{openpgp.spaced(openpgp.SNAPSHOTS_FINGERPRINT)}.", f.openpgp_key_file, {"nullable": True}),
    ),
    *_concern(
        "ros_install",
        _enabled("ros_install", "Install the ROS 2 packages."),
        ("ubuntu_release", "24.04", str,
         "The Ubuntu release the roster expects; a host running another release is stopped.",
         f.ubuntu_release, {"allowed": ", ".join(p.release for p in distros.PLATFORMS)}),
        ("ros_distro", None, str, "ROS 2 distro; None: the release's default ("
         + ", ".join(f"{p.codename}: {p.distro}" for p in distros.PLATFORMS) + ").",
         f.ros_distro, {"nullable": True, "allowed": ", ".join(sorted(distros.DISTRO_RELEASES))}),
        ("ros_variant", None, str,
         "Variant to install; None: the robot profile's for the host's side (demo, turtlebot3: "
         "desktop on the main, with RViz and rqt; ros-base on a robot).", f.ros_variant, {"nullable": True}),
        ("ros_variant_main", "desktop", str,
         "Deprecated (the role is not a key's business): set ros_variant on the main host, or in a "
         "profile's main side. Still honoured, with a warning, when a roster sets it.", f.ros_variant),
        ("ros_variant_robot", "ros-base", str,
         "Deprecated: set ros_variant on the robot, or in a profile's robot side. Still honoured, "
         "with a warning, when a roster sets it.", f.ros_variant),
        ("ros_dev_tools", True, bool, "Install ros-dev-tools (colcon, rosdep, vcstool)."),
        ("ros_extra_packages", [], list,
         'Extra apt packages for every host; "{distro}" is replaced, e.g. "ros-{distro}-turtlesim".',
         f.package_template, {"item": str, "allowed": "Debian package names"}),
        ("class_lock_auto", False, bool,
         "Let a run take the class lock (classroom.lock beside the roster) itself: a group (ROS distro, "
         "architecture) the lock lacks is written into it at the end of a run in which a host of the group "
         "converged without failure, as `roslab lock` would take it (never on --dry); a locked group is never "
         "rewritten by a run (`roslab lock --update` moves it). false: only `roslab lock` takes it.",
         None, {"levels": ("classroom",)}),
        ("class_lock_debs_dir", "~/.cache/roslab/class-debs", str,
         "Where the controller keeps the class lock's .debs, a folder per class (its roster's folder) and "
         "group: `roslab lock` keeps each "
         "locked package apt downloaded onto the group's hosts (what the runs installed), `--update` the "
         "versions it moves to, each checked against the SHA256 of the index apt verified. A host whose "
         "sources no longer list a locked version (packages.ros.org after a sync) is served the kept .debs "
         "as a local apt source. A folder of its own inside the home directory, the roster's folder or the "
         "temporary directory; null: nothing kept (such a host stops, naming the version).", f.cache_dir,
         {"levels": ("classroom",), "nullable": True}),
    ),
    *_concern(
        "robot_base",
        _enabled("robot_base", "Set up the robot's base computer where the profile has one (TurtleBot 4: "
                 "usb0 at 192.168.186.3/24, chrony serving the Create 3, and the Create 3's domain, namespace, "
                 "middleware and NTP server over its HTTP API)."),
    ),
    *_concern(
        "robot_profile",
        _enabled("robot_profile", "Apply the robot profile's udev rules and the login user's groups."),
        ("robot_profile", "demo", str,
         "What the team's hosts run: a built-in profile (one file each in roslab/profiles/data; "
         "docs/robots.md lists them) or one of the roster's own `profiles:`. Its settings (e.g. "
         "turtlebot3_model, lds_model) are set beside it.",
         f.pattern(r"[a-z][a-z0-9_]{0,62}", "a profile name"),
         {"allowed": "a built-in profile (docs/robots.md) or a roster's profile"}),
        ("board", None, str,
         f"The board the host is: {boards.in_words()}; None: not said (nothing is checked). "
         + " ".join(f"Ubuntu's first image for a {b.title} is {b.first_release}." for b in boards.BOARDS
                    if b.first_release), f.choice(*boards.NAMES),
         {"nullable": True}),
        ("ros_environment", {}, dict,
         "Extra environment variables for the login user's shell (~/.bashrc block), the nodes' "
         "service and `roslab verify`, e.g. {RCUTILS_COLORIZED_OUTPUT: \"1\"}; each value is "
         "written with the escaping its destination needs. Names are two or more words of capitals "
         "and digits (LAB_ROBOT_NAME); ROS's and the middleware's (set by ros_middleware, "
         "ros_domain_id, ros_discovery_mode...), the prompt's, the loader's and interpreters' are "
         "refused (roslab.formats.variable).", f.environment,
         {"allowed": "WORD_WORD: one line of text"}),
        ("profile_os_tweaks", False, bool,
         "Apply the OS changes the robot's maker recommends, as the profile lists them (turtlebot3, "
         "from ROBOTIS's e-Manual: mask systemd-networkd-wait-online and the sleep targets; a 2 GiB "
         "/swapfile where the host has 2 GiB of memory or less). Turning it off later undoes nothing."),
        ("ros_packages_check", True, bool,
         "Before connecting, check every ROS package the roster or a profile names against the "
         "distro's rosdistro file (from rosdistro_index_url; offline: the controller's copy)."),
    ),
    *_concern(
        "profile_services",
        _enabled("profile_services",
                 "Install the robot profile's own services (osr_startup, micro_ros_agent) and run those "
                 "whose settings say so (osr_calibrated, esp32_present)."),
    ),
    *_concern(
        "rosdep",
        _enabled("rosdep", "Initialise rosdep and keep the login user's rosdep cache fresh."),
        ("rosdep_package", "python3-rosdep", str,
         "Package that provides rosdep when ros-dev-tools did not (ros_dev_tools: false).", f.debian_package),
        ("rosdep_sources_list_url", None, str,
         "URL of rosdep's sources list (20-default.list), fetched by the controller; None: "
         "the official one. A file:// URL must name a .list file inside the roster's folder.",
         f.url(("http", "https", "file"), file_suffix=".list"), {"nullable": True}),
        ("rosdistro_index_url", None, str,
         "URL of the rosdistro index (ROSDISTRO_INDEX_URL); None: rosdep's built-in default.",
         f.http_url, {"nullable": True}),
        ("rosdep_data_from_controller", True, bool,
         "The controller downloads rosdep's sources list, the rule files it lists and the rosdistro "
         "index (with the host's distro) once, keeps them in rosdep_cache_dir and copies them to "
         "each host; false: every host downloads them itself (rosdep init, rosdep update)."),
        ("rosdep_cache_dir", "~/.cache/roslab/rosdep", str,
         "Where the controller keeps rosdep's data (on the machine running pyinfra): a folder of its "
         "own inside the home directory, the roster's folder or the temporary directory.",
         f.cache_dir),
        ("rosdep_update_max_age", 7 * SECONDS_PER_DAY, int,
         "Seconds before the login user's rosdep cache counts as stale and is updated again; "
         "the controller checks its kept copy of rosdep's data on each run with a conditional request "
         "(nothing downloaded when unchanged), and uses it when upstream does not answer.",
         f.int_range(0, 365 * SECONDS_PER_DAY, " s")),
    ),
    *_concern(
        "sources",
        _enabled("sources", "Build the repositories of the host's .repos files (its robot profile's `sources`, "
                            "the roster's workspace_sources) in the login user's underlay workspace."),
        ("workspace_sources", [], list,
         "Extra vcstool .repos files (relative to the roster) whose repositories the hosts build in "
         "their underlay workspace, beside their robot profile's; each version a commit (40 hex digits) "
         "or a tag, never a branch.", _repos_file, {"item": str}),
        ("source_url_rewrites", {}, dict,
         "Where the controller fetches a repository from instead, like git's url.<base>.insteadOf: "
         "{\"https://github.com/\": \"http://mirror.lab/git/github.com/\"} (the longest matching prefix wins); "
         "the lock file and every message keep the URL the .repos file gives. A file:// replacement (and "
         "every URL it makes) leads inside the roster's folder, not .roslab-state, like a file:// source.",
         _url_rewrites,
         {"levels": ("classroom",)}),
        ("source_pins", {}, dict,
         "Repository path (as its .repos file names it) -> the commit (40 hex digits) or tag to build "
         "instead of the file's: moves a robot profile's pin without editing the profile (a newer "
         "release, a lab mirror's own tag).", _source_pins),
        ("sources_cache_dir", "~/.cache/roslab/sources", str,
         "Where the controller keeps a bare mirror of each repository and the lock file (tag -> commit, "
         "commit -> sha256 of its archive); offline: true builds from it alone. A folder of its own inside "
         "the home directory, the roster's folder or the temporary directory.", f.cache_dir,
         {"levels": ("classroom",)}),
        ("sources_underlay_dir", "~/roslab_underlay", str,
         "The login user's underlay workspace (inside their home): the repositories in src/, built with "
         "colcon; the student's workspace (workspace_dir) overlays it.", f.home_path,
         {"allowed": "~/ and a path inside the home"}),
        ("underlay_builder", None, str,
         "The host that builds the underlay for every host that needs the same one (same distro, "
         "architecture, pinned sources, build settings, underlay path), which receive its build from the "
         "controller; None: the group's first host in the roster with the memory the profile asks for. "
         "It must need the same underlay as the hosts it is set on.",
         f.host_label, {"nullable": True, "allowed": "a host of the same underlay group"}),
        ("sources_rosdep_install", True, bool,
         "Run `rosdep install --from-paths src --ignore-src -y` in the underlay when its sources changed."),
        ("sources_fetch_timeout", 300, int,
         "Seconds the controller waits for one git command (ls-remote, fetch) of one repository.",
         f.int_range(5, 3600, " s"), {"levels": ("classroom",)}),
    ),
    *_concern(
        "python_env",
        _enabled("python_env",
                 "Install the robot profile's Python requirements (python_packages) into its venv "
                 "(python_venv, with the system's site packages, so ROS's Python is seen): downloaded "
                 "once per class by the controller into its wheelhouse and copied to the hosts, which "
                 "install from those files only."),
        ("python_index_url", "https://pypi.org/simple", str,
         "The package index (PEP 503 simple API) the controller downloads the requirements from: "
         "PyPI, or a classroom's mirror (devpi, a piwheels mirror...). The hosts never use it.",
         f.http_url, {"levels": ("classroom",)}),
        ("python_wheelhouse_dir", "~/.cache/roslab/wheelhouse", str,
         "Where the controller keeps the downloaded wheels and sdists, one folder per host "
         "platform (machine, glibc, Python) and requirement set (on the machine running pyinfra): "
         "a folder of its own inside the home directory, the roster's folder or the temporary "
         "directory. offline: true installs from it alone.", f.cache_dir, {"levels": ("classroom",)}),
        ("python_sdist_build_packages", ["python3-dev", "gcc"], list,
         "apt packages a host needs to build a requirement the index has no wheel for (RPi.GPIO and "
         "smbus are sdists only): installed only where the wheelhouse holds an sdist.",
         f.debian_package, {"item": str, "allowed": "Debian package names"}),
    ),
    *_concern(
        "shell_env",
        _enabled("shell_env", "Write the ROS 2 environment block into the login user's ~/.bashrc."),
        ("ros_domain_id", None, int,
         "ROS_DOMAIN_ID, a team setting: each team has its own, so teams on one network do "
         "not see each other's topics. None: a free ID from 1 to 101 derived from the team's name "
         "(stable across runs and however the teams are ordered; `roslab check` shows it); two teams "
         "on one ID are refused.", f.domain_id, {"levels": ("classroom", "team"), "nullable": True}),
        ("ros_automatic_discovery_range", "SUBNET", str,
         "ros_discovery_mode multicast, Jazzy and later: ROS_AUTOMATIC_DISCOVERY_RANGE. On Humble, "
         "LOCALHOST becomes ROS_LOCALHOST_ONLY=1 and the others export nothing.",
         f.choice("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")),
        ("ros_static_peers", [], list,
         "Jazzy and later: ROS_STATIC_PEERS, hosts to discover without multicast (unreliable on WiFi); "
         "ros_discovery_mode static adds them to the team's own hosts (on Humble too).",
         f.static_peer, {"item": str, "allowed": "host names or IP addresses"}),
    ),
    *_concern(
        "discovery",
        _enabled("discovery",
                 "Write each host's middleware discovery files (/etc/roslab/discovery) and run the team's "
                 "discovery server or Zenoh router as a service on its main; false: the variables are "
                 "still set, the files and services are yours."),
        ("ros_middleware", discovery.DEFAULT_MIDDLEWARE, str,
         "The class's ROS middleware (RMW_IMPLEMENTATION everywhere, its package installed): "
         "rmw_fastrtps_cpp (Fast DDS, ROS's default), rmw_cyclonedds_cpp (Cyclone DDS) or rmw_zenoh_cpp "
         "(Zenoh, with a router on each team's main). One for the whole class.",
         f.choice(*discovery.MIDDLEWARES), {"levels": ("classroom",)}),
        ("ros_discovery_mode", discovery.DEFAULT_MODE, str,
         "How a team's hosts find each other: multicast (DDS's own discovery), static (each host's "
         "peers are its team's hosts: for networks without multicast, Humble and Jazzy alike), "
         "discovery_server (a Fast DDS discovery server on the team's main) or localhost (nothing "
         "leaves the host: a simulation-only host). Set for the class, overridden per team; a host "
         "may only be set to localhost.",
         f.choice(*discovery.MODES)),
        ("ros_discovery_server_port", discovery.DEFAULT_SERVER_PORT, int,
         "UDP port of each team's discovery server (ros_discovery_mode discovery_server).",
         f.int_range(1024, 65535), {"levels": ("classroom",)}),
        ("ros_zenoh_router_port", discovery.DEFAULT_ROUTER_PORT, int,
         "TCP port of each team's Zenoh router (ros_middleware rmw_zenoh_cpp).",
         f.int_range(1024, 65535), {"levels": ("classroom",)}),
    ),
    *_concern(
        "ssh_identity",
        _enabled("ssh_identity", "Install and run sshd, authorise the teacher's keys, set hostname and /etc/hosts."),
        ("teacher_ssh_keys", [], list,
         "The teacher's public keys for the login user's authorized_keys: key lines "
         '("ssh-ed25519 AAAA... teacher") or paths to .pub files on the machine running pyinfra '
         "(regular files of at most 64 KiB holding only key lines).",
         f.teacher_key, {"item": str, "allowed": "key lines or .pub files"}),
        ("manage_hostname", True, bool, "Set the hostname to the host's name in the roster."),
        ("manage_etc_hosts", True, bool,
         "List every classroom host in /etc/hosts (a marked block) so names resolve without DNS."),
    ),
    *_concern(
        "ssh_hardening",
        _enabled("ssh_hardening",
                 "Make sshd key-only with no root login (a managed drop-in that sorts before cloud-init's), "
                 "applied only after a key login worked in the same run and `sshd -t` accepts it; "
                 "false: sshd's configuration is left as it is."),
        ("ssh_password_login", False, bool,
         "Keep SSH password (and keyboard-interactive) login, e.g. for students logging in from lab "
         "PCs; false: keys only."),
        ("ssh_permit_root_login", "no", str,
         "sshd's PermitRootLogin: no, or prohibit-password (root with a key only).",
         f.choice("no", "prohibit-password")),
    ),
    *_concern(
        "network",
        _enabled("network", "Manage the network of hosts that have a network_address (or network_method: dhcp)."),
        ("network_backend", "auto", str,
         "Who applies the configuration: auto (whoever is in charge on the host), netplan "
         "(netplan with systemd-networkd) or networkmanager (NetworkManager).",
         f.choice("auto", "netplan", "networkmanager")),
        ("network_interface", None, str, "Interface to configure; None: eth0 for ethernet, wlan0 for wifi.",
         f.interface_name, {"nullable": True}),
        ("network_kind", "ethernet", str, "ethernet or wifi.", f.choice("ethernet", "wifi")),
        ("network_method", "static", str, "static (network_address) or dhcp.", f.choice("static", "dhcp")),
        ("network_address", None, str,
         "The host's fixed address, e.g. 192.168.50.11/24 (usually set per host); None: the network "
         "is left alone. The prefix may come from network_prefix instead.", f.ip_interface,
         {"nullable": True, "allowed": "IPv4 address[/prefix]"}),
        ("network_prefix", None, int,
         "Prefix length for a network_address given without one, e.g. 24 (usually classroom-wide).",
         f.int_range(8, 32), {"nullable": True}),
        ("network_gateway", None, str,
         "Default gateway (the router), inside the address's subnet; None: no default route.",
         f.ip_address, {"nullable": True, "allowed": "IP address"}),
        ("network_nameservers", [], list, "DNS servers, e.g. [192.168.50.1].", f.ip_address,
         {"item": str, "allowed": "IP addresses"}),
        ("network_ipv6", "auto", str,
         "IPv6: auto (router advertisements and DHCPv6), disabled, or ignore (not configured).",
         f.choice("auto", "disabled", "ignore")),
        ("wifi_ssid", None, str, "The WiFi network's name, for network_kind: wifi.", f.wifi_ssid,
         {"nullable": True, "allowed": "1 to 32 bytes, one line"}),
        ("wifi_password_secret", None, str,
         "Name of the WiFi password in the secrets file (never the password itself).", f.secret_name,
         {"nullable": True}),
        ("wifi_regulatory_domain", None, str,
         "The WiFi regulatory domain, the country the Pis are in (like DE or GB): without one a "
         "Pi's WiFi keeps to the channels and power allowed everywhere. Written into the seed's "
         "network-config (`roslab seed`).", f.country_code, {"nullable": True}),
        ("network_confirm_timeout", 60, int,
         "Seconds the host waits for the controller to reach it at its new address before it "
         "restores its previous configuration by itself.", f.int_range(10, 3600, " s")),
        ("network_disable_cloud_init", True, bool,
         "Stop cloud-init from rewriting the network at boot (its 50-cloud-init.yaml is kept as a backup)."),
        ("network_backups_keep", 5, int,
         "How many backups of replaced network files each host keeps under /var/backups/roslab/network "
         "(one per change; the oldest are removed).", f.int_range(1, 100)),
    ),
    *_concern(
        "workspace",
        _enabled("workspace", "Copy nodes/ into the login user's workspace, build it and run the role's launch."),
        ("workspace_dir", "~/ros2_ws", str, "The login user's colcon workspace, inside their home.",
         f.home_path, {"allowed": "~/ and a path inside the home"}),
        ("workspace_nodes_dir", None, str,
         "Controller directory whose ROS packages are copied into the workspace's src/; None: "
         "this checkout's nodes/. It must hold a ROS package (a top-level folder with a package.xml) "
         "and may not be /, the home directory or a folder holding the roster.",
         f.nodes_dir, {"nullable": True}),
        ("workspace_colcon_args", ["--executor", "sequential"], list,
         "Arguments after `colcon build`; a sequential build is what colcon advises on a Pi.",
         f.colcon_argument, {"item": str, "allowed": ", ".join(f.COLCON_OPTIONS) + " (with their values)"}),
        ("workspace_rosdep_install", True, bool,
         "Run `rosdep install --from-paths src --ignore-src -y` when a package.xml changed."),
        ("nodes_service_enabled", True, bool,
         "Run the role's launch as the systemd service roslab-nodes, restarted whenever one of its nodes ends."),
        ("nodes_launch", None, str,
         "What the host's service runs: `ros2 launch <package> <launch file>`; None: its robot "
         "profile's launch for its side (demo: roslab_bringup main.launch.py / robot.launch.py, "
         "turtlebot3: the robot's bringup, nothing on the main).", f.launch,
         {"allowed": "<package> <name>.launch.py or <name>_launch.py (.xml, .yaml)", "nullable": True}),
        ("nodes_launch_main", None, str,
         "Deprecated: set nodes_launch on the main host (or in a profile). Still honoured, with a "
         "warning, for main hosts.", f.launch, {"allowed": "<package> <name>.launch.py or <name>_launch.py (.xml, .yaml)", "nullable": True}),
        ("nodes_launch_robot", None, str,
         "Deprecated: set nodes_launch on the robot (or in a profile). Still honoured, with a "
         "warning, for robots.", f.launch, {"allowed": "<package> <name>.launch.py or <name>_launch.py (.xml, .yaml)", "nullable": True}),
        ("nodes_verify_topic", None, str,
         "The topic `roslab verify` expects each team's main host to hear from its robot; None: the "
         "robot profile's (demo: /chatter, turtlebot3: /scan).", f.ros_topic, {"nullable": True}),
        ("nodes_verify_type", None, str,
         "The message type on that topic; None: the robot profile's (demo: std_msgs/msg/String, "
         "whose text must be a robot's greeting; turtlebot3: sensor_msgs/msg/LaserScan, where any "
         "message passes).", f.ros_message_type, {"nullable": True}),
        ("nodes_verify_timeout", 20, int, "Seconds `roslab verify` waits for a message on that topic.",
         f.int_range(1, 600, " s")),
    ),
]

SETTINGS: dict[str, Setting] = {setting.key: setting for setting in SCHEMA}
if len(SETTINGS) != len(SCHEMA):  # a key declared twice would silently shadow the first
    raise RuntimeError("a setting is declared twice in roslab.settings.SCHEMA")

# The concerns whose settings are deploy settings (not the roster's own keys).
ROSTER_CONCERNS = ("roster", "connection")
# The settings a host's data holds: the roster's own keys (name, role, address...) are not host
# data, the loader turns them into roslab_role, ssh_hostname and the like (HOST_KEYS).
HOST_SETTINGS = [s for s in SCHEMA if s.concern != "roster"]
DEPLOY_CONCERNS = tuple(dict.fromkeys(s.concern for s in SCHEMA if s.concern not in ROSTER_CONCERNS))


@dataclass(frozen=True)
class HostKey:
    """A key of a host's data that no roster sets and the deploys read: the roster loader
    derives it (the host's identity, the lists of hosts, the resolved profile). It is a field
    of roslab.host_settings.HostSettings beside the settings; None when a hand-made inventory
    lacks it."""

    key: str
    annotation: str  # the field's type, as roslab/host_fields.py writes it
    kind: type  # what a value must be (checked when a host's settings are built)
    doc: str
    secret: bool = False  # kept out of the settings' repr: a hand-made inventory may give it as plain text


HOST_KEYS: list[HostKey] = [
    HostKey("roslab_team", "str", str, "The host's team (also a pyinfra group, `-` becomes `_`)."),
    HostKey("roslab_role", "str", str, "main or robot (also a pyinfra group)."),
    HostKey("roslab_hostname", "str", str, "The host's name in the roster (= pyinfra's host name)."),
    HostKey("roslab_classroom_hosts", "list[dict[str, str | None]]", list,
            "Every host of the roster, {name, address} (for /etc/hosts)."),
    HostKey("roslab_team_hosts", "list[dict[str, str | None]]", list,
            "The hosts of the host's own team, {name, address, role}."),
    HostKey("roslab_ubuntu_release", "str", str, "The Ubuntu release the roster expects, e.g. 24.04."),
    HostKey("roslab_expected_distro", "str", str,
            "The ROS distro the roster implies (ros_distro, else the release's default)."),
    HostKey("roslab_roster_path", "str", str, "The roster file (moved addresses are recorded beside it)."),
    HostKey("roslab_sources", "list[dict[str, Any]]", list,
            "The repositories of the host's .repos files (its profile side's and workspace_sources)."),
    HostKey("roslab_verify_source", "str", str, "What publishes the profile's verify topic, for verify to name."),
    HostKey("roslab_verify_publisher", "str", str, "The node that must publish the verify topic (\"\" or None: any)."),
    HostKey("roslab_profile", "ResolvedProfile", dict,
            "The host's robot profile resolved for its side, distro and settings (roslab.profiles.resolve); "
            "host data carries it as a plain mapping, this field as the dataclass."),
    HostKey("ssh_hostname", "str", str, "Where pyinfra connects to the host (its roster address or the "
            "last confirmed one)."),
    HostKey("wifi_password", "object", object, "The WiFi password wifi_password_secret names, read from the "
            "secrets file by the roster loader (a roslab.secrets.Secret, masked in every output; checked as a "
            "WPA password by roslab.network.settings).", secret=True),
    HostKey("console_password", "object", object, "The console password console_password_secret names, read "
            "from the secrets file by the roster loader (a roslab.secrets.Secret); `roslab seed` writes only its "
            "hash.", secret=True),
]


def annotation(setting: Setting) -> str:
    """A setting's type as Python writes it: `str | None`, `list[str]`, `dict[str, str]`.

    A roster or connection key may be absent from a host's data (pyinfra's own default), so
    it may be None whatever its declaration says."""
    names = {str: "str", int: "int", bool: "bool"}
    if setting.kind is list:
        assert setting.item is not None, f"{setting.key}: a list setting declares its item type"
        text = f"list[{names[setting.item]}]"
    elif setting.kind is dict:
        text = "dict[str, str]"  # every mapping setting maps names to text (their checks say so)
    else:
        text = names[setting.kind]
    return text + (" | None" if setting.nullable or setting.concern in ROSTER_CONCERNS else "")


def defaults(concern: str | None = None) -> dict:
    """Defaults of one concern's settings, or of every deploy setting (fresh copies)."""
    import copy

    return {
        s.key: copy.deepcopy(s.default) for s in SCHEMA
        if (s.concern == concern if concern else s.concern not in ROSTER_CONCERNS)
    }


@functools.cache
def keys_at(level: str) -> dict[str, Setting]:
    """The settings a roster may set at `level` (classroom, team or host): one dict per level,
    read-only (the roster reader asks once per host)."""
    return {s.key: s for s in SCHEMA if level in s.levels}


# No list or mapping setting needs more entries than this (a classroom's extra packages,
# static peers, keys); a longer one is a mistake, refused before it is checked item by item.
MAX_ITEMS = 256

_TYPE_NAMES = {str: "a string", int: "an integer", bool: "true or false", list: "a list",
               dict: "a mapping"}


def type_problem(value, kind) -> str | None:
    """Why `value` is not of `kind`, or None. YAML's bools are not integers here."""
    if kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if ok:
        return None
    shown = repr(value) if not isinstance(value, (dict, list)) else type(value).__name__
    hint = ""
    if kind is str and isinstance(value, bool):
        hint = " (YAML reads yes/no/on/off/true/false as true or false: quote it)"
    elif kind is str and isinstance(value, (int, float)):
        hint = f' (YAML reads {value} as a number: quote it, "{value}")'
    elif kind is int and isinstance(value, str) and value.strip().lstrip("-").isdigit() \
            and value.strip().isascii():
        digits = value.strip()
        plain = str(int(digits, 10))
        hint = " (remove the quotes)" if plain == digits else f" (write {plain}, without quotes)"
    return f"must be {_TYPE_NAMES[kind]}, not {shown}{hint}"


def check_value(setting: Setting, value, context: f.Context | None = None) -> str | None:
    """Why `value` is not a legal value of `setting`, or None. Never raises."""
    context = context or f.Context()
    if value is None:
        return None if setting.nullable else f"must be {_TYPE_NAMES[setting.kind]}, not null"
    problem = type_problem(value, setting.kind)
    if problem:
        return problem
    if setting.kind in (list, dict) and len(value) > MAX_ITEMS:
        return f"has {len(value)} entries; at most {MAX_ITEMS} are allowed"
    try:
        if setting.item is not None:
            for index, element in enumerate(value):
                problem = type_problem(element, setting.item)
                if problem is None and setting.check:
                    problem = setting.check(element, context)
                if problem:
                    return f"item {index + 1}: {problem}"
            whole = getattr(setting.check, "whole", None)  # a list read as one (colcon's options)
            return whole(value, context) if whole else None
        if setting.kind is dict:
            if not all(isinstance(key, str) for key in value):
                return "keys must be strings"
        return setting.check(value, context) if setting.check else None
    except OSError as error:  # a path this machine cannot even look up (too long, no permission)
        return f"cannot be checked on this machine: {error.strerror or type(error).__name__}"
    except (RecursionError, ValueError, TypeError) as error:  # a check must not end the run
        return f"cannot be checked: {type(error).__name__}"
