"""`roslab status [ROSTER]`: the classroom at a glance, as a table and as a page.

    roslab status [ROSTER] [--limit NAME ...] [--html FILE] [--listen [--listen-timeout S]]

Per host: whether SSH reaches it, its Ubuntu release, the ROS 2 distros installed, its
domain ID (the one its `roslab-nodes` service runs with, else the roster's), the address
it is reached at, the service's state, and the last deploy.py run on it with its time and
the last successful one (`roslab.reporting.runs`, recorded on this machine by each run). A table on
the terminal, and one self-contained HTML page (inline CSS and SVG, no script, no server,
nothing fetched) with a picture of each team: its main host, its robots, what the main
host hears. Default page: `<roster dir>/.roslab-state/status.html`.

Read-only and bounded: the hosts are reached the way deploy.py reaches them (the roster's
ssh user, key, port, known_hosts and host key policy, and a host the network deploy moved
at its recorded address), all in parallel, each within `HOST_BOUND` seconds, with one
command (`StatusProbe`, no sudo). A host that cannot be reached is a row that says why.
`--listen` adds `roslab verify`'s check on each main host whose profile names a topic
(`roslab.cli.verify.hear`: the topics it lists and whether its robot's message arrives, waiting
the roster's `nodes_verify_timeout` unless `--listen-timeout` says), a second bounded command.
Each host is judged by what its roster and robot profile run there (`roslab.cli.host_services`):
a TurtleBot3's or a sim main runs no nodes service and is green without one; a stopped
discovery server, Zenoh router or profile service is named in its row and its team's line.
With a class lock beside the roster (roslab.class_lock), the probe also asks apt about the locked
packages, and each locked group's date and how far the archives moved past it follow the table
(roslab.cli.status_lock).

Exit status: 0 when every host answered and none failed its last recorded run; 1 when one
did not answer, one's last run failed, or the roster has errors. A host
whose last run failed is red on the page (its box, its row and the chips above).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shlex
import sys
import textwrap
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import yaml
from pyinfra.api import FactBase

from roslab.host_settings import HostSettings
from roslab.roster import Classroom, RosterError, display_path, group_names, inventory_groups
from roslab.ops.boot_config import RebootRecord, parse_reboot_record, reboot_pending
from roslab.reporting.runs import RunRecord, now_utc, read_runs, runs_path
from roslab.reporting import waiting
from roslab.cli import launch_journal, status_lock
from roslab.cli.host_services import host_services, profile_name, runs_nodes, services_not_started
from roslab.cli.verify import (
    CHATTER_TYPE, SERVICE_RUNNING, TeamResult, check_bound, hear, parse_check_output, service_state,
    stopped_service_line,
)
from roslab.ros.workspace import NODES_SERVICE

# Bounds, in seconds.
CONNECT_TIMEOUT = 8  # the TCP connection (paramiko's timeout; the deploys use pyinfra's 10)
PROBE_TIMEOUT = 15  # the probe command
HOST_BOUND = 30  # everything on one host, connection included (without --listen)
# --listen: seconds a main host waits for its robot's message, unless --listen-timeout says: the
# roster's nodes_verify_timeout, as roslab verify waits (Fast DDS discovery alone can take more
# than 5 s on a busy host). LISTEN_TIMEOUT is for a host without one (a hand-made inventory).
LISTEN_TIMEOUT = 20

STATUS_PAGE = "status.html"
# Topics every ROS 2 graph has: not worth a line in the picture.
BACKGROUND_TOPICS = ("/rosout", "/parameter_events")
MAX_TOPICS = 8  # topic lines in a team's picture
UNREACHABLE = "unreachable"
# Results in runs.yaml of a host whose last run did not finish it.
FAILED_RESULTS = ("failed", "interrupted")


class StatusProbe(FactBase):
    """
    What `roslab status` shows of one host, in one read-only command that needs no root:
    ``{"probed": bool, "os": {...os-release...}, "ros": ["jazzy"], "unit": {...}}``.

    ``ros`` lists each ``/opt/ros/<distro>`` with a ``setup.bash``; ``unit`` is systemd's
    view of the nodes' service (``LoadState``, ``ActiveState``, ``SubState``, ``Result``,
    ``Environment``); ``probed`` is False when nothing came back.
    """

    @staticmethod
    def default():
        return parse_probe([])

    def command(self, service: str = NODES_SERVICE, others: tuple[str, ...] = (), launches: tuple[str, ...] = (),
                underlay: str = "", base_url: str = "", lock_packages: tuple[str, ...] | None = None) -> str:
        return probe_script(service, others, launches, underlay, base_url, lock_packages)

    def process(self, output):
        return parse_probe(output)


def probe_script(service: str = NODES_SERVICE, others: tuple[str, ...] = (), launches: tuple[str, ...] = (),
                 underlay: str = "", base_url: str = "", lock_packages: tuple[str, ...] | None = None) -> str:
    """`others`: the host's other services (roslab.cli.host_services: its discovery server or Zenoh
    router, its profile's), each read into a `## unit <name>` section; `launches`: those that
    run `ros2 launch`, whose journal's last lines go into a `## journal <name>` section (which
    of the launch's nodes died, roslab.cli.launch_journal); `underlay`: the shell word naming its
    underlay's origin record (`origin_file`), read into `## underlay`; `base_url`: the robot's
    base (a TurtleBot 4's Create 3, roslab.profiles.robot_base), whose /api/about goes into `## base`;
    `lock_packages` (None without a class lock): the locked packages whose `apt-cache policy` goes,
    after the host's architecture, into `## apt-policy` (roslab.cli.status_lock)."""
    return "; ".join([
        *(("echo '## underlay'", f"head -c 200 {underlay} 2>/dev/null; echo") if underlay else ()),
        "echo '## os-release'",
        "cat /etc/os-release 2>/dev/null",
        "echo '## ros'",
        "for setup in /opt/ros/*/setup.bash; do [ -f \"$setup\" ] && printf '%s\\n' \"${setup%/setup.bash}\"; done",
        "echo '## unit'",
        "systemctl show --property=LoadState,ActiveState,SubState,Result,Environment "
        f"{shlex.quote(service)} 2>/dev/null",
        *(part for other in others for part in (
            f"echo {shlex.quote(f'## unit {other}')}",
            f"systemctl show --property=LoadState,ActiveState,SubState,Result {shlex.quote(other)} 2>/dev/null")),
        *(part for unit in launches for part in (
            f"echo {shlex.quote(f'## journal {unit}')}", launch_journal.command(shlex.quote(unit)))),
        *(("echo '## base'", f"curl -fsS -m 3 {shlex.quote(base_url + '/api/about')} 2>/dev/null || "
           "echo '#no-answer'; echo") if base_url else ()),
        *((f"echo '## {status_lock.SECTION}'", status_lock.policy_command(lock_packages))
          if lock_packages is not None else ()),
        "echo '## reboot'",
        REBOOT_RECORD_COMMAND,
        "echo '## end'",
        "exit 0",
    ])


# The host's "reboot needed" record (roslab.ops.boot_config), readable without sudo.
REBOOT_RECORD_COMMAND = RebootRecord().command()


def parse_os_release(lines) -> dict[str, str]:
    values = {}
    for line in lines:
        key, sep, value = line.partition("=")
        if not sep or not key.strip().isidentifier():
            continue
        try:
            words = shlex.split(value)
        except ValueError:
            words = [value.strip("\"'")]
        values[key.strip()] = " ".join(words)
    return values


def parse_environment(text: str) -> dict[str, str]:
    """systemd's `Environment=` property (`A=1 B="x y"`) as a dict."""
    try:
        words = shlex.split(text)
    except ValueError:
        words = text.split()
    return dict(word.split("=", 1) for word in words if "=" in word)


def parse_probe(lines) -> dict:
    sections: dict[str, list[str]] = {}
    section = None
    for line in lines:
        if line.startswith("## "):
            section = line[3:].strip()
            sections.setdefault(section, [])
            continue
        if section is not None:
            sections[section].append(line)
    def properties(lines) -> dict:
        return dict(line.split("=", 1) for line in lines if "=" in line)

    return {
        "probed": "end" in sections,
        "os": parse_os_release(sections.get("os-release", [])),
        "ros": sorted({os.path.basename(line.strip()) for line in sections.get("ros", []) if line.strip()}),
        "unit": properties(sections.get("unit", [])),
        "units": {name.removeprefix("unit "): properties(lines) for name, lines in sections.items()
                  if name.startswith("unit ")},
        "journals": {name.removeprefix("journal "): lines for name, lines in sections.items()
                     if name.startswith("journal ")},
        "reboot": parse_reboot_record(sections.get("reboot", [])),
        "underlay": parse_origin(sections.get("underlay", [])),
        "base": parse_base(sections["base"]) if "base" in sections else None,
        "apt_policy": status_lock.parse_policy(sections[status_lock.SECTION])
        if status_lock.SECTION in sections else None,
    }


def parse_base(lines) -> dict:
    """The `## base` section: ``{"answered": bool, "firmware": "I.0.0.FastDDS" or None}``."""
    from roslab.profiles.robot_base import firmware_generation

    text = "\n".join(lines).strip()
    answered = bool(text) and not text.endswith("#no-answer")
    return {"answered": answered, "firmware": firmware_generation(text) if answered else None}


# "built here <digest>" or "shipped from <host> <digest>" (roslab.sources.underlay.origin_line)
_ORIGIN = re.compile(r"(built here|shipped from ([A-Za-z0-9][A-Za-z0-9.-]{0,252})) ([0-9a-f]{64})", re.ASCII)


def parse_origin(lines) -> dict | None:
    """{"builder": host or None (built here), "digest"} from the underlay's origin record, or None."""
    for line in lines:
        match = _ORIGIN.fullmatch(line.strip())
        if match:
            return {"builder": match.group(2), "digest": match.group(3)}
    return None


def origin_file(settings: HostSettings) -> str:
    """The shell word naming the host's underlay origin record (roslab.sources.underlay.ORIGIN), read
    as the SSH user: `~user/...` for a folder in the login user's home; "" without an underlay."""
    from roslab.sources.underlay import ORIGIN
    from roslab.sources.groups import roster_inputs

    if roster_inputs(settings) is None:
        return ""
    user = settings.login_user or settings.ssh_user or ""
    folder = str(settings.sources_underlay_dir or "~/roslab_underlay")
    if not re.fullmatch(r"[a-z_][a-z0-9_-]{0,31}", user):
        return ""
    inside = f"{folder[2:]}/{ORIGIN}" if folder.startswith("~/") else None
    return f"~{user}/{shlex.quote(inside)}" if inside else shlex.quote(f"{folder}/{ORIGIN}")


# What was found
# --------------


@dataclass
class HostStatus:
    """One host as `roslab status` found it."""

    name: str
    team: str
    role: str
    address: str
    roster_domain: int | None = None
    domain_assigned: bool = False  # roslab chose the team's ID from its name
    discovery_mode: str | None = None  # the roster's ros_discovery_mode for this host
    middleware: str | None = None  # the class's ros_middleware
    expected_release: str | None = None
    expected_distro: str | None = None
    reachable: bool = False
    error: str | None = None  # why it was not reached, or why the probe came back empty
    probe: dict = field(default_factory=lambda: parse_probe([]))
    run: RunRecord | None = None
    heard: dict | None = None  # --listen, main hosts: roslab.cli.verify's NodesHeard
    listen_error: str | None = None
    # What the host runs by its roster and robot profile (roslab.cli.host_services).
    profile: str = "demo"
    runs_nodes: bool = True
    other_services: list = field(default_factory=list)  # HostService, beside roslab-nodes
    listens: bool = True  # a main whose profile names a topic to hear (not sim)
    # What publishes the topic it hears, and the node that must (an ESP32 team's board), as verify names them
    verify_source: str = ""
    verify_publisher: str = ""
    # (service, why) of its profile's services the roster leaves off (an uncalibrated rover)
    not_started: list = field(default_factory=list)
    listen_timeout: int = LISTEN_TIMEOUT  # --listen: seconds its check waits for a message
    # The shell word naming its underlay's origin record (origin_file); "" when it builds none.
    underlay: str = ""
    base: dict | None = None  # the robot profile's base (roslab.profiles.robot_base), robot hosts only
    # The class lock's packages its probe asks apt about (roslab.cli.status_lock); None: no lock.
    lock_packages: tuple[str, ...] | None = None

    @property
    def release(self) -> str | None:
        return self.probe["os"].get("VERSION_ID") or None

    @property
    def codename(self) -> str | None:
        os_release = self.probe["os"]
        return os_release.get("UBUNTU_CODENAME") or os_release.get("VERSION_CODENAME") or None

    @property
    def is_ubuntu(self) -> bool:
        return self.probe["os"].get("ID") == "ubuntu"

    @property
    def reboot_needed(self) -> str | None:
        """Why the host waits for a reboot (a change recorded in its current boot), or None."""
        record = self.probe.get("reboot") or {}
        if not (self.reachable and self.probe["probed"] and reboot_pending(record)):
            return None
        return "; ".join(record["reasons"]) or "a change waits for a reboot"

    @property
    def distros(self) -> list[str]:
        return self.probe["ros"]

    @property
    def unit(self) -> dict:
        return self.probe["unit"]

    @property
    def service(self) -> str:
        return service_state(self.unit) if self.reachable and self.probe["probed"] else "?"

    @property
    def nodes(self) -> str:
        """The NODES cell: the service's state, or that the profile runs none here."""
        if not self.runs_nodes and self.reachable and self.probe["probed"]:
            return f"none ({self.profile} {self.role})"
        return self.service

    def other_states(self) -> list[tuple]:
        """(HostService, state) of its other services, as systemd has them."""
        if not (self.reachable and self.probe["probed"]):
            return [(service, "?") for service in self.other_services]
        units = self.probe.get("units") or {}
        return [(service, service_state(units.get(service.unit) or {})) for service in self.other_services]

    def node_deaths(self) -> list[tuple]:
        """(host, unit, node, times, why) of each node that died in the last minute in a running
        launch service of its profile (the rover's roboclaw_wrapper without its serial port)."""
        journals = self.probe.get("journals") or {}
        return [(self.name, service.unit.removesuffix(".service"), node, count, why)
                for service, state in self.other_states() if service.launch and state == SERVICE_RUNNING
                for node, (count, why) in launch_journal.died_nodes(journals.get(service.unit) or []).items()]

    def launch_failures(self) -> list[str]:
        """One line per node of `node_deaths`."""
        return [launch_journal.death_line(unit, node, count, why) for _, unit, node, count, why in self.node_deaths()]

    def services_stopped(self) -> list[tuple]:
        """(HostService, state) of its other services that do not run."""
        return [(service, state) for service, state in self.other_states() if state != SERVICE_RUNNING]

    @property
    def runs_what_it_should(self) -> bool:
        """Reached, and every service its roster gives it runs (none at all is fine)."""
        if not (self.reachable and self.probe["probed"]):
            return False
        return (not self.runs_nodes or self.service.startswith("active")) and not self.services_stopped()

    @property
    def runs_all_it_should(self) -> bool:
        """runs_what_it_should, and no service of its profile waits for a setting (an uncalibrated
        rover runs nothing yet): what the page shows green and counts as running."""
        return self.runs_what_it_should and not self.not_started

    @property
    def domain(self) -> int | None:
        """The domain ID the nodes' service runs with, if the host has the service."""
        if self.unit.get("LoadState") != "loaded":
            return None
        value = parse_environment(self.unit.get("Environment", "")).get("ROS_DOMAIN_ID")
        return int(value) if value is not None and value.isdigit() else None

    @property
    def distro(self) -> str | None:
        """The ROS 2 distro that matters here: the roster's, if installed, else the one installed."""
        if self.expected_distro in self.distros:
            return self.expected_distro
        return self.distros[0] if self.distros else None


@dataclass
class Cell:
    text: str
    level: str = "plain"  # ok, warn, bad, muted, plain: the page colours it


COLUMNS = ("TEAM", "HOST", "ROLE", "ADDRESS", "SSH", "UBUNTU", "ROS", "DOMAIN", "DISCOVERY", "NODES",
           "UNDERLAY", "LAST RUN", "LAST SUCCESS", "NOTE")


def ago(moment: datetime | None, now: datetime) -> str:
    """'5 min ago', '3 h ago', '2 days ago' (or 'never')."""
    if moment is None:
        return "never"
    seconds = (now - moment).total_seconds()
    if seconds < 0:
        return "in the future"  # the controller's clock moved back
    if seconds < 60:
        return "just now"
    if seconds < 3600:
        return f"{int(seconds // 60)} min ago"
    if seconds < 2 * 86400:
        return f"{int(seconds // 3600)} h ago"
    return f"{int(seconds // 86400)} days ago"


def when(moment: datetime | None, now: datetime) -> str:
    """A recorded time in this machine's local time, and how long ago it was."""
    if moment is None:
        return "never"
    return f"{moment.astimezone().strftime('%Y-%m-%d %H:%M')} ({ago(moment, now)})"


def service_level(service: str) -> str:
    if service == "?":
        return "muted"
    if service.startswith("active"):
        return "ok"
    if service.startswith("failed"):
        return "bad"
    return "warn"  # not installed, inactive, activating


def host_cells(host: HostStatus, now: datetime) -> dict[str, Cell]:
    """The host's row, the same for the terminal and the page. Each cell that finds trouble adds
    its note to `notes`, in column order, for the NOTE cell at the end."""
    notes: list[str] = []
    probed = host.reachable and host.probe["probed"]
    cells = {
        "TEAM": Cell(host.team), "HOST": Cell(host.name), "ROLE": Cell(host.role),
        "ADDRESS": Cell(host.address),
    }
    cells["SSH"] = ssh_cell(host, notes)
    cells["UBUNTU"] = ubuntu_cell(host, probed, notes)
    cells["ROS"] = ros_cell(host, probed, notes)
    cells["DOMAIN"] = domain_cell(host, notes)
    cells["DISCOVERY"] = discovery_cell(host, notes)
    cells["NODES"] = nodes_cell(host, probed)
    for service, state in host.services_stopped() if probed else ():
        notes.append(stopped_service_line(host.name, service, state))
    failures = host.launch_failures() if probed else []
    notes += failures

    cells["UNDERLAY"] = underlay_cell(host, probed)
    cells["LAST RUN"] = last_run_cell(host.run, now, notes)
    cells["LAST SUCCESS"] = last_success_cell(host.run, now)
    if probed and host.probe.get("base") is not None:
        notes.append(base_note(host))
    if host.reboot_needed:
        notes.append(f"reboot needed: {host.reboot_needed}")
    if host.listen_error:
        notes.append(host.listen_error)
    level = ("bad" if not host.reachable or last_run_failed(host)
             else "warn" if host.reboot_needed or failures or (probed and host.services_stopped()) else "plain")
    cells["NOTE"] = Cell("; ".join(notes), level)
    return cells


def base_note(host: HostStatus) -> str:
    """The robot's base in one note: its firmware (and whether it is the distro's), or silence."""
    from roslab.profiles.robot_base import RobotBase, firmware_problem

    base, seen = RobotBase.from_data(host.base), host.probe["base"]
    if base is None:  # probed only for a profile with a base
        return ""
    if not seen["answered"]:
        return f"{base.kind} at {base.base_address}: no answer"
    if not seen["firmware"]:
        return f"{base.kind} answers, firmware version not shown"
    problem = firmware_problem(seen["firmware"], host.expected_distro or "", base)
    return problem or f"{base.kind} firmware {seen['firmware']}"


def ssh_cell(host: HostStatus, notes: list[str]) -> Cell:
    """Whether the host answered over SSH; a host that answered but whose probe said nothing gets a note."""
    if not host.reachable:
        notes.append(host.error or UNREACHABLE)
        return Cell(UNREACHABLE, "bad")
    if not host.probe["probed"]:
        notes.append(host.error or "the status command returned nothing")
    return Cell("ok", "ok")


def ubuntu_cell(host: HostStatus, probed: bool, notes: list[str]) -> Cell:
    """The host's Ubuntu release, checked against the one the roster expects."""
    if not probed:
        return Cell("?", "muted")
    if not host.is_ubuntu:
        name = host.probe["os"].get("PRETTY_NAME") or host.probe["os"].get("ID") or "not Ubuntu"
        notes.append("not Ubuntu")
        return Cell(name, "bad")
    text = " ".join(part for part in (host.release, host.codename) if part) or "?"
    level = "ok"
    if host.expected_release and host.release != host.expected_release:
        level = "bad"
        notes.append(f"the roster expects Ubuntu {host.expected_release}")
    return Cell(text, level)


def ros_cell(host: HostStatus, probed: bool, notes: list[str]) -> Cell:
    """The ROS 2 distros installed; a warning when the roster's is not among them."""
    if not probed:
        return Cell("?", "muted")
    if not host.distros:
        return Cell("none", "warn")
    level = "ok" if not host.expected_distro or host.expected_distro in host.distros else "warn"
    if level == "warn":
        notes.append(f"the roster expects ROS 2 {host.expected_distro}")
    return Cell(", ".join(host.distros), level)


def domain_cell(host: HostStatus, notes: list[str]) -> Cell:
    """The ROS domain the host's nodes run on, checked against the roster's (or the roster's alone,
    saying where it came from, when the host does not tell)."""
    roster_domain = "-" if host.roster_domain is None else str(host.roster_domain)
    if host.domain is None:
        return Cell(f"{roster_domain} ({'auto' if host.domain_assigned else 'roster'})", "muted")
    if host.roster_domain is not None and host.domain != host.roster_domain:
        notes.append(f"its nodes run on domain {host.domain}, the roster says {roster_domain}")
        return Cell(str(host.domain), "bad")
    return Cell(str(host.domain), "ok")


def nodes_cell(host: HostStatus, probed: bool) -> Cell:
    """The nodes' service state on a host that runs them; what the roster gives it otherwise."""
    if host.runs_nodes:
        return Cell(host.service, service_level(host.service))
    if host.not_started and probed:  # the rover before its calibration: runs nothing yet, and should
        return Cell(f"none: {', '.join(service for service, _why in host.not_started)} not started", "warn")
    return Cell(host.nodes, "ok" if probed else "muted")


def last_run_cell(run: RunRecord | None, now: datetime, notes: list[str]) -> Cell:
    """The last recorded run's result and time; a failed run notes the step and reason it gave."""
    if run is None or run.last_run is None:
        return Cell("never", "muted")
    result = run.result or "?"
    level = "bad" if result in FAILED_RESULTS else {"ok": "ok", "changed": "ok"}.get(result, "warn")
    if result in FAILED_RESULTS and (run.step or run.reason):
        notes.append(f"last run {result} in \"{run.step or '?'}\": {run.reason or '?'}")
    return Cell(f"{result} {when(run.last_run, now)}", level)


def last_success_cell(run: RunRecord | None, now: datetime) -> Cell:
    """When the host last ran without failing; a warning if it has runs but no success."""
    if run is None or run.last_success is None:
        return Cell("never", "warn" if run is not None and run.last_run else "muted")
    return Cell(when(run.last_success, now), "ok")


def underlay_cell(host: HostStatus, probed: bool) -> Cell:
    """Where the host's underlay came from: built here, or shipped from its group's builder
    (roslab.sources.ship), with its digest (short); "-" for a host that builds none."""
    from roslab.sources.groups import short

    if not host.underlay:
        return Cell("-", "muted")
    if not probed:
        return Cell("?", "muted")
    origin = host.probe.get("underlay")
    if origin is None:
        return Cell("none yet", "warn")
    where = f"shipped from {origin['builder']}" if origin["builder"] else "built here"
    return Cell(f"{where} {short(origin['digest'])}", "ok")


def discovery_cell(host: HostStatus, notes: list[str]) -> Cell:
    """The host's discovery mode from the roster, checked against the middleware its nodes run with."""
    mode = host.discovery_mode or "-"
    running = parse_environment(host.unit.get("Environment", "")).get("RMW_IMPLEMENTATION") \
        if host.unit.get("LoadState") == "loaded" else None
    if running and host.middleware and running != host.middleware:
        notes.append(f"its nodes run {running}, the roster says {host.middleware}")
        return Cell(f"{mode} ({running})", "bad")
    return Cell(mode, "plain" if running is None else "ok")


def format_table(hosts: list[HostStatus], now: datetime) -> str:
    rows = [COLUMNS] + [tuple(host_cells(host, now)[column].text for column in COLUMNS) for host in hosts]
    widths = [max(len(row[index]) for row in rows) for index in range(len(COLUMNS))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * width for width in widths))
    return "\n".join(lines)


# Reading the hosts
# -----------------


def host_statuses(classroom: Classroom, groups: dict, limit: list[str] | None = None) -> list[HostStatus]:
    """One HostStatus per roster host (in roster order) that `limit` selects, without
    contacting any host. `groups`: the roster's `inventory_groups`, as deploy.py gets them."""
    from roslab.reach import limit_selection, names_of

    addresses = {name: data["ssh_hostname"] for entries in groups.values() for name, data in entries}
    selected = None if not limit else set(limit_selection(names_of(groups), limit)[0])
    statuses = []
    for host in classroom.hosts:
        if selected is not None and host.name not in selected:
            continue
        typed = host.settings
        statuses.append(HostStatus(
            name=host.name, team=host.team, role=host.role,
            address=str(addresses.get(host.name) or host.address),
            roster_domain=host.ros_domain_id,
            domain_assigned=host.domain_assigned,
            discovery_mode=typed.ros_discovery_mode,
            middleware=typed.ros_middleware,
            expected_release=host.ubuntu_release, expected_distro=host.distro,
            profile=profile_name(typed), runs_nodes=runs_nodes(typed),
            other_services=[service for service in host_services(typed) if service.kind != "nodes"],
            listens=bool(typed.nodes_verify_topic),
            verify_source=typed.roslab_verify_source or "", verify_publisher=typed.roslab_verify_publisher or "",
            not_started=services_not_started(typed),
            listen_timeout=int(typed.nodes_verify_timeout or LISTEN_TIMEOUT),
            underlay=origin_file(typed),
            base=typed.roslab_profile.base if typed.roslab_profile is not None else None,
        ))
    return statuses


def probe(groups: dict, statuses: list[HostStatus], listen: bool = False,
          listen_timeout: int | None = None, host_bound: int = HOST_BOUND) -> None:
    """Fill in what each host says, all hosts at once, each within `host_bound` seconds
    (plus the listening check's own bound with `listen`). `listen_timeout`: seconds every main
    waits for its message; None: each its own (`HostStatus.listen_timeout`)."""
    from gevent import monkey

    monkey.patch_all()  # as pyinfra's CLI does: SSH to every host at once (a no-op when done)
    import gevent
    from pyinfra.api.state import MAX_PARALLEL

    from roslab.reach import roster_state

    # Every host at once (as many as open files allow), so each host's bound is the whole wait.
    parallel = max(1, min(len(statuses), MAX_PARALLEL))
    state = roster_state(groups, [status.name for status in statuses],
                         CONNECT_TIMEOUT=min(CONNECT_TIMEOUT, host_bound), PARALLEL=parallel)
    inventory = state.inventory
    if listen_timeout is not None:
        for status in statuses:
            status.listen_timeout = listen_timeout
    bound = host_bound
    if listen:
        bound += check_bound(max(status.listen_timeout for status in statuses)) + 30
    pyinfra_logger = logging.getLogger("pyinfra")
    level = pyinfra_logger.level
    pyinfra_logger.setLevel(logging.CRITICAL)  # every host's trouble is its row, not a log line
    try:
        by_name = {host.name: host for host in inventory}
        jobs = {state.pool.spawn(_probe_host, state, by_name[status.name], status, listen, status.listen_timeout,
                                 bound): status for status in statuses}
        rounds = -(-len(statuses) // parallel)
        if listen:
            longest = max(status.listen_timeout for status in statuses)
            print(f"roslab status: reading {len(statuses)} hosts, each main listening for its robot's topic "
                  f"(all at once, each up to {longest} s for a message, after the ROS tools start)",
                  file=sys.stderr, flush=True)
        # never silent: a line every few seconds names the hosts still being read
        waiting.joined({job: status.name for job, status in jobs.items()}, "roslab status: still reading",
                       timeout=rounds * bound + 5)
        for job, status in jobs.items():
            if not job.ready():
                job.kill(block=False)
                status.reachable = status.reachable and status.probe["probed"]
                status.error = status.error or f"no answer within {bound} s"
        disconnect = [state.pool.spawn(host.disconnect) for host in inventory if host.connected]
        gevent.joinall(disconnect, timeout=10)
    finally:
        pyinfra_logger.setLevel(level)


def _probe_host(state, host, status: HostStatus, listen: bool, listen_timeout: int, bound: int) -> None:
    import gevent
    from pyinfra.api.exceptions import ConnectError
    from pyinfra.api.facts import get_fact
    from pyinfra.context import ctx_host

    # gevent's Timeout(seconds, False) ends the block silently (documented); its stubs take
    # only an exception there.
    with ctx_host.use(host), gevent.Timeout(bound, False):  # type: ignore[arg-type]
        try:
            host.connect(show_errors=False, raise_exceptions=True)
        except ConnectError as error:
            status.error = explained(host.name, one_line(error.args[0] if error.args else error))
            return
        except Exception as error:  # noqa: BLE001 - a host's trouble is its row
            status.error = one_line(f"{type(error).__name__}: {error}")
            return
        status.reachable = True
        state.activate_host(host)
        try:
            status.probe = get_fact(
                state, host, StatusProbe,
                kwargs={"others": tuple(service.unit for service in status.other_services),
                        "launches": tuple(service.unit for service in status.other_services if service.launch),
                        "underlay": status.underlay,
                        "base_url": f"http://{status.base['base_address']}" if status.base else "",
                        "lock_packages": status.lock_packages,
                        "_sudo": False, "_timeout": min(PROBE_TIMEOUT, bound), "_ignore_errors": True},
                apply_failed_hosts=False,
            )
        except Exception as error:  # noqa: BLE001
            status.error = one_line(f"{type(error).__name__}: {error}")
            return
        if not status.probe["probed"]:
            status.error = "the status command returned nothing"
            return
        if listen and status.role == "main" and status.listens:
            if not status.distro:
                status.listen_error = "no ROS 2 installed: not listened"
                return
            try:
                status.heard = hear(host, distro=status.distro, timeout=listen_timeout)
            except Exception as error:  # noqa: BLE001
                status.listen_error = one_line(f"listening failed: {error}")
    if not status.probe["probed"] and not status.error:  # the bound ended it
        status.error = f"no answer within {bound} s"
    elif (listen and status.role == "main" and status.listens and status.probe["probed"] and status.distro
          and status.heard is None and not status.listen_error):
        status.listen_error = f"listening did not finish within {bound} s"


def explained(host_name: str, message: str) -> str:
    """A connection error as deploy.py's log shows it: a refused host key becomes roslab's
    instruction (`roslab trust ...`, `roslab forget ...`; roslab.ssh.identity)."""
    from roslab.ssh import identity

    record = logging.LogRecord("pyinfra", logging.ERROR, __file__, 0, f"[{host_name}] {message}", (), None)
    identity.explainer().filter(record)
    return one_line(record.getMessage().removeprefix(f"[{host_name}] ").removeprefix("roslab: "))


def one_line(text) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= 400 else text[:397] + "..."


# The team pictures and the page
# ------------------------------

BOX_WIDTH, BOX_HEIGHT, BOX_GAP = 250, 105, 18  # room for five lines: the nodes' state may take two
MAIN_X, ROBOT_X, MARGIN = 16, 480, 16
LINE = 16  # height of a text line in the picture
TEXT_LIMIT = 32  # characters of a line in a box
TOPIC_LIMIT, TOPIC_LINES = 60, 3  # characters and lines of one thing the main host hears


def clip(text: str, limit: int = TEXT_LIMIT) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"


def wrapped(text: str, limit: int = TEXT_LIMIT, lines: int = 2) -> list[str]:
    """`text` in lines of at most `limit` characters, broken at spaces (or inside a word too
    long for a line), at most `lines` of them, the last clipped (the box's title holds it all)."""
    return textwrap.wrap(text, limit, max_lines=lines, placeholder=" \u2026") or [""]


def last_run_failed(host: HostStatus) -> bool:
    """Whether the last deploy.py run recorded for the host failed."""
    return host.run is not None and host.run.result in FAILED_RESULTS


def box_level(host: HostStatus) -> str:
    """The colour of the host's box: red when it is unreachable or its last run failed (the
    legend says red means failed), else its nodes' service state."""
    if not host.reachable or last_run_failed(host):
        return "bad"
    states = [state for _, state in host.other_states()] + ([host.service] if host.runs_nodes else [])
    levels = [service_level(state) for state in states]
    if "bad" in levels:
        return "bad"
    return "ok" if host.runs_all_it_should else "warn"


def host_box(host: HostStatus, x: int, y: int) -> dict:
    if not host.reachable:
        facts = UNREACHABLE
    elif not host.probe["probed"]:
        facts = "no answer"
    else:
        ubuntu = f"Ubuntu {host.release}" if host.is_ubuntu and host.release else "not Ubuntu"
        facts = f"{ubuntu} \u00b7 ROS {host.distro or 'none'}"
    lines = [
        {"text": clip(host.name), "class": "name"},
        {"text": clip(f"{host.role} \u00b7 {host.address}"), "class": "detail"},
        {"text": clip(facts), "class": "detail"},
        # "osr_calibrated is false (it runs when ...)": the setting that starts it fits the box
        *({"text": line, "class": "detail"} for line in wrapped(
            f"nodes: {host.nodes}" if not host.not_started
            else f"not started: {host.not_started[0][1].split(' is ')[0]}")),
    ]
    return {
        "x": x, "y": y, "width": BOX_WIDTH, "height": BOX_HEIGHT, "level": box_level(host),
        "title": f"{host.name} ({host.role}, team {host.team})"
                 + (f": reboot needed ({host.reboot_needed})" if host.reboot_needed else "")
                 + "".join(f"; {service} not started: {why}" for service, why in host.not_started),
        "host": host.name,
        "lines": [{**line, "x": x + 12, "y": y + 22 + index * 19} for index, line in enumerate(lines)],
    }


def team_picture(team: str, hosts: list[HostStatus], listen: bool, topic: str = "/chatter",
                 message_type: str = CHATTER_TYPE, listen_timeout: int | None = None) -> dict:
    """Coordinates and texts of one team's SVG: main on the left, robots on the right, arrows
    from each robot to the main host labelled with what the main host hears."""
    main = next((host for host in hosts if host.role == "main"), None)
    robots = [host for host in hosts if host.role != "main"]
    rows = max(1, len(robots))
    main_y = MARGIN + (rows - 1) * (BOX_HEIGHT + BOX_GAP) // 2
    boxes = [main_box(main, main_y)]
    result = team_result(team, hosts, main, robots, topic, message_type, listen_timeout)
    # Listened for real: the main host answered with a ROS 2 runtime (else nothing is known).
    listened = listen and main is not None and bool((main.heard or {}).get("ros"))
    nothing_to_hear = main is not None and not main.listens
    heard_robots = result.heard_robots()
    arrows = []
    for index, robot in enumerate(robots):
        y = MARGIN + index * (BOX_HEIGHT + BOX_GAP)
        boxes.append(host_box(robot, ROBOT_X, y))
        state, label = robot_heard(robot, heard_robots, topic, listened, nothing_to_hear)
        arrows.append(robot_arrow(index, len(robots), y, main_y, state, label))

    # What the main host hears, under its box.
    topics_y = main_y + BOX_HEIGHT + 22
    topic_lines = [part for line in heard_lines(main, result, listen, nothing_to_hear)
                   for part in wrapped(line, TOPIC_LIMIT, TOPIC_LINES)]
    texts = [{"x": MAIN_X + 4, "y": topics_y + index * LINE, "text": line}
             for index, line in enumerate(topic_lines)]
    if not robots:
        texts.append({"x": ROBOT_X, "y": main_y + BOX_HEIGHT // 2 + 4, "text": "no robot in this team"})
    height = max(MARGIN + rows * (BOX_HEIGHT + BOX_GAP), topics_y + len(topic_lines) * LINE) + MARGIN
    verdict, verdict_level = team_verdict(hosts, result, listen, listened, nothing_to_hear)
    return {
        "name": team, "width": ROBOT_X + BOX_WIDTH + MARGIN, "height": height,
        "boxes": boxes, "arrows": arrows, "texts": texts,
        "verdict": verdict, "verdict_level": verdict_level,
        "domain": next((str(h.roster_domain) + (" auto" if h.domain_assigned else "")
                        for h in hosts if h.roster_domain is not None), "-"),
        "discovery": team_discovery(hosts),
        "no_robot": not robots,
    }


def main_box(main: HostStatus | None, main_y: int) -> dict:
    """The main host's box, or a muted placeholder saying the team has none."""
    if main is not None:
        return host_box(main, MAIN_X, main_y)
    return {"x": MAIN_X, "y": main_y, "width": BOX_WIDTH, "height": BOX_HEIGHT, "level": "muted",
            "title": "no main host", "host": "", "lines": [
                {"text": "no main host", "class": "name", "x": MAIN_X + 12, "y": main_y + 22}]}


def team_result(team: str, hosts: list[HostStatus], main: HostStatus | None, robots: list[HostStatus],
                topic: str, message_type: str, listen_timeout: int | None) -> TeamResult:
    """The team's check as roslab verify judges it, from what the status probe read on its hosts."""
    result = TeamResult(team, main=main.name if main else None, robots=sorted(r.name for r in robots),
                        topic=topic, services={host.name: host.service for host in hosts},
                        message_type=message_type,
                        timeout=listen_timeout or (main.listen_timeout if main else LISTEN_TIMEOUT),
                        without_service={host.name for host in hosts if not host.runs_nodes},
                        other_services=[(host.name, service, state) for host in hosts
                                        for service, state in host.other_states()])
    result.not_started = [(host.name, service, why) for host in hosts for service, why in host.not_started]
    result.node_deaths = [death for host in hosts for death in host.node_deaths()]
    if main is not None:
        result.heard = main.heard
        result.listens, result.profile = main.listens, main.profile
        result.source, result.publisher = main.verify_source, main.verify_publisher
        if not main.reachable:
            result.error = f"{main.name} is {UNREACHABLE}"
        elif main.listen_error:
            result.error = main.listen_error
    return result


def robot_heard(robot: HostStatus, heard_robots: list[str], topic: str, listened: bool,
                nothing_to_hear: bool) -> tuple[str, str]:
    """A robot's arrow: its state (ok, bad, unknown) and label, from what the main host heard."""
    if nothing_to_hear:
        return "unknown", "nothing to hear"
    if not listened:
        return "unknown", f"{topic}: not checked"
    if robot.name in heard_robots:
        return "ok", f"{topic}: heard"
    return "bad", f"{topic}: not heard"


def robot_arrow(index: int, robot_count: int, y: int, main_y: int, state: str, label: str) -> dict:
    """The arrow from the robot box at `y` to the main box, its label halfway."""
    # Each robot's arrow ends at its own point of the main box's edge, so labels stay apart.
    start = (ROBOT_X - 2, y + BOX_HEIGHT // 2)
    end = (MAIN_X + BOX_WIDTH + 8, main_y + (index + 1) * BOX_HEIGHT // (robot_count + 1))
    return {"x1": start[0], "y1": start[1], "x2": end[0], "y2": end[1], "state": state,
            "label": clip(label, 28), "label_x": (start[0] + end[0]) // 2,
            "label_y": (start[1] + end[1]) // 2 - 7}


def heard_lines(main: HostStatus | None, result: TeamResult, listen: bool, nothing_to_hear: bool) -> list[str]:
    """The lines under the main host's box: the topics it sees (listed by ROS, as verify's "topics
    seen" column; a topic seen is not a message heard: the verdict says that), or why none are shown."""
    heard = (main.heard if main is not None else None) or parse_check_output([])
    if nothing_to_hear:
        return [f"topics seen: not checked ({main.profile if main is not None else 'no main host'}: no topic)"]
    if not listen:
        return ["topics seen: not checked (roslab status --listen)"]
    if main is None or main.heard is None:
        return [f"topics seen: {result.verdict()}"]
    if not heard["ros"]:
        return ["topics seen: no ROS 2 runtime on the main host"]
    topics = [name for name in heard["topics"] if name not in BACKGROUND_TOPICS]
    lines = ["topics seen:" if topics else "topics seen: none"]
    lines += [f"  {name}" for name in topics[:MAX_TOPICS]]
    if len(topics) > MAX_TOPICS:
        lines.append(f"  and {len(topics) - MAX_TOPICS} more")
    return lines


def team_verdict(hosts: list[HostStatus], result: TeamResult, listen: bool, listened: bool,
                 nothing_to_hear: bool) -> tuple[str, str]:
    """The team's one-line verdict and its level; hosts whose last run failed come first."""
    if listen or nothing_to_hear:
        verdict = result.verdict()
        verdict_level = ("ok" if result.passed else "warn" if result.unchecked
                         else "bad" if listened or nothing_to_hear else "warn")
    else:
        verdict, verdict_level = services_verdict(hosts)
    failed = sum(last_run_failed(host) for host in hosts)
    if failed:
        verdict = f"{failed} of {len(hosts)} hosts failed their last run; " + verdict
        verdict_level = "bad"
    return verdict, verdict_level


def services_verdict(hosts: list[HostStatus]) -> tuple[str, str]:
    """Without --listen: how many of the team's hosts run what their roster gives them (a
    TurtleBot3's main runs nothing and counts), naming a stopped discovery server or router."""
    good = sum(host.runs_what_it_should for host in hosts)
    verdict = f"{good} of {len(hosts)} hosts run their services"
    stopped = [stopped_service_line(host.name, service, state) for host in hosts
               if host.reachable and host.probe["probed"] for service, state in host.services_stopped()]
    if stopped:
        verdict += "; " + "; ".join(stopped)
    return verdict, "ok" if good == len(hosts) else "bad" if stopped else "warn"


def team_discovery(hosts: list[HostStatus]) -> str:
    """The team's discovery mode(s) and the class's middleware, as the team's heading shows them."""
    modes = sorted({host.discovery_mode for host in hosts if host.discovery_mode})
    middleware = next((host.middleware for host in hosts if host.middleware), None)
    return ", ".join([*modes, *([middleware] if middleware else [])]) or "-"


def page_context(classroom_name: str | None, roster: str, hosts: list[HostStatus], now: datetime,
                 listen: bool = False, topics: dict[str, str] | None = None,
                 warnings: list[str] | None = None, checklists: list[dict] | None = None,
                 message_types: dict[str, str] | None = None, listen_timeout: int | None = None) -> dict:
    """Everything the page shows, computed here (the template only loops and tests).

    `checklists`: per host, its robot profile's steps done by hand (`checklists()`)."""
    teams: dict[str, list[HostStatus]] = {}
    for host in hosts:
        teams.setdefault(host.team, []).append(host)
    topics = topics or {}
    reachable = sum(host.reachable for host in hosts)
    running = sum(host.runs_all_it_should for host in hosts)
    failed = sum(last_run_failed(host) for host in hosts)
    return {
        "title": f"roslab status: {classroom_name}" if classroom_name else "roslab status",
        "classroom": classroom_name or "Classroom",
        "roster": roster,
        "generated": now.astimezone().strftime("%Y-%m-%d %H:%M:%S %Z"),
        "counts": [
            {"text": f"{len(teams)} teams, {len(hosts)} hosts", "level": "plain"},
            {"text": f"{reachable} reachable", "level": "ok" if reachable == len(hosts) else "bad"},
            {"text": f"{running} running their services", "level": "ok" if running == len(hosts) else "warn"},
            {"text": f"{failed} failed in their last run" if failed else "no failed last run",
             "level": "bad" if failed else "ok"},
        ],
        "listen": listen,
        "teams": [team_picture(name, members, listen, topics.get(name, "/chatter"),
                               (message_types or {}).get(name, CHATTER_TYPE), listen_timeout)
                  for name, members in teams.items()],
        "columns": COLUMNS,
        "rows": [{"host": host.name, "cells": [host_cells(host, now)[column] for column in COLUMNS]}
                 for host in hosts],
        "warnings": warnings or [],
        "checklists": checklists or [],
        "lock": [],  # the class lock's lines (roslab.cli.status_lock.lock_lines), set by run
    }


def checklists(classroom: Classroom, names: set[str] | None = None) -> list[dict]:
    """Per host, the robot profile's steps that need the hardware attached (done by hand)."""
    result = []
    for host in classroom.hosts:
        profile = host.settings.roslab_profile
        if profile is not None and profile.checklist and (names is None or host.name in names):
            result.append({"host": host.name, "profile": profile.name, "items": list(profile.checklist)})
    return result


def format_checklists(lists: list[dict]) -> str:
    lines = ["Hardware checklist (by hand, with the hardware attached):"]
    for entry in lists:
        lines.append(f"  {entry['host']} ({entry['profile']}):")
        lines += [f"    [ ] {item}" for item in entry["items"]]
    return "\n".join(lines)


def item_parts(text: str) -> list[dict]:
    """A checklist item's text and its `code` spans (a command to copy), for the page."""
    pieces = text.split("`")
    if len(pieces) % 2 == 0:  # an unpaired backtick: the text as it is
        return [{"text": text, "code": False}]
    return [{"text": piece, "code": bool(index % 2)} for index, piece in enumerate(pieces) if piece]


def render_page(context: dict) -> str:
    from roslab.templating import render_html

    return render_html("status.html.j2", item_parts=item_parts, **context)


def write_page(path: Path, text: str) -> None:
    """Write the page atomically (a teacher's browser may be reloading it)."""
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            out.write(text)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def default_page_path(roster_path: Path) -> Path:
    return runs_path(roster_path).parent / STATUS_PAGE


# The command
# -----------


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    from roslab.reach import add_roster_argument

    parser = parser or argparse.ArgumentParser(prog="roslab status", description=__doc__.splitlines()[0])
    add_roster_argument(parser)
    parser.add_argument("--html", metavar="FILE",
                        help=f"where to write the page (default: .roslab-state/{STATUS_PAGE} beside the roster)")
    parser.add_argument("--timeout", type=int, default=HOST_BOUND, metavar="S",
                        help=f"seconds each host gets to answer, connection included (default {HOST_BOUND})")
    parser.add_argument("--listen", action="store_true",
                        help="also check what each main host hears (roslab verify's check; slower)")
    parser.add_argument("--listen-timeout", type=int, default=None, metavar="S",
                        help="--listen: seconds to wait for the robot's message (default: the roster's "
                             f"nodes_verify_timeout, {LISTEN_TIMEOUT} s unless set, as roslab verify waits)")
    return parser


def run(args: argparse.Namespace) -> int:
    from roslab.reach import RosterProblem, limit_problem, load_classroom

    try:
        classroom = load_classroom(args.roster, "status")
    except RosterProblem as roster_problem:
        print(roster_problem, file=sys.stderr)
        return 1
    path = classroom.path
    bad_timeout = timeout_problem(args)
    if bad_timeout:
        print(bad_timeout, file=sys.stderr)
        return 2
    warnings = [str(warning) for warning in classroom.warnings]
    try:
        # Once: it also brings the classroom's known_hosts up to date, as deploy.py's inventory does.
        groups = inventory_groups(classroom)
        problem = limit_problem(group_names(classroom), args.limit, "roslab status")
        statuses = [] if problem else host_statuses(classroom, groups, args.limit)
    except RosterError as error:  # a broken addresses.yaml or known_hosts
        print(error, file=sys.stderr)
        return 1
    if problem or not statuses:
        print(problem or f"roslab status: {display_path(path)} has no host", file=sys.stderr)
        return 2
    attach_recorded_runs(classroom, statuses, warnings)
    lock = attach_lock(classroom, statuses)

    probe(groups, statuses, listen=args.listen, listen_timeout=args.listen_timeout, host_bound=args.timeout)

    now = now_utc()
    context = status_context(classroom, statuses, now, args, warnings)
    context["lock"] = status_lock.lock_lines(lock, statuses, now)
    print_status(classroom, statuses, now, context, args.listen, warnings)

    page = Path(args.html) if args.html else default_page_path(classroom.path)
    try:
        write_page(page, render_page(context))
    except OSError as error:
        print(f"roslab status: cannot write {page}: {error.strerror or error}", file=sys.stderr)
        return 1
    print(f"\npage: {display_path(page)}")
    problems = status_problems(statuses)
    for problem in problems:
        print(problem, file=sys.stderr)
    return 1 if problems else 0


def timeout_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with --timeout or --listen-timeout, if anything (both are bounded seconds)."""
    for option, value in (("--timeout", args.timeout), ("--listen-timeout", args.listen_timeout)):
        if value is not None and not 1 <= value <= 600:
            return f"roslab status: {option} must be 1 to 600 seconds"
    return None


def attach_recorded_runs(classroom: Classroom, statuses: list[HostStatus], warnings: list[str]) -> None:
    """Give each host its last recorded run; an unreadable record is a warning, not a failure."""
    try:
        runs = read_runs(classroom.path)
    except (OSError, ValueError, yaml.YAMLError) as error:
        runs = {}
        warnings.append(f"{display_path(runs_path(classroom.path))}: cannot read the recorded runs "
                        f"({getattr(error, 'strerror', None) or 'not a mapping of host to run'})")
    for status in statuses:
        status.run = runs.get(status.name)


def attach_lock(classroom: Classroom, statuses: list[HostStatus]):
    """The class lock beside the roster (None without one; a broken one was refused with the
    roster, naming file and field), and on each host the locked packages its probe asks about."""
    from roslab.class_lock import lock_beside

    lock = lock_beside(str(classroom.path))
    if lock is None:
        return None
    for status in statuses:
        status.lock_packages = status_lock.asked_packages(lock, status.expected_distro)
    return lock


def status_context(classroom: Classroom, statuses: list[HostStatus], now: datetime,
                   args: argparse.Namespace, warnings: list[str]) -> dict:
    """The page's data, with each team's topic and message type from its main host's settings."""
    topics = {host.team: host.settings.nodes_verify_topic or "/chatter"
              for host in classroom.hosts if host.role == "main"}
    message_types = {host.team: host.settings.nodes_verify_type or CHATTER_TYPE
                     for host in classroom.hosts if host.role == "main"}
    return page_context(classroom.name, display_path(classroom.path), statuses, now, args.listen, topics,
                        warnings, checklists(classroom, {status.name for status in statuses}), message_types,
                        args.listen_timeout)


def print_status(classroom: Classroom, statuses: list[HostStatus], now: datetime, context: dict,
                 listen: bool, warnings: list[str]) -> None:
    """The terminal's report: warnings, the title, the table, checklists and, with --listen, each
    team's verdict."""
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    title = f"Classroom {classroom.name!r}" if classroom.name else "Classroom"
    print(f"{title} ({display_path(classroom.path)}), {now.astimezone().strftime('%Y-%m-%d %H:%M:%S')}")
    print(format_table(statuses, now))
    if context.get("lock"):
        print()
        print("\n".join(line["text"] for line in context["lock"]))
    if context["checklists"]:
        print()
        print(format_checklists(context["checklists"]))
    if listen:
        print()
        for picture in context["teams"]:
            print(f"team {picture['name']}: {picture['verdict']}")


def status_problems(statuses: list[HostStatus]) -> list[str]:
    """One line per kind of trouble that makes `roslab status` exit 1: hosts unreachable,
    hosts whose last recorded run failed."""
    problems = []
    unreachable = [status.name for status in statuses if not status.reachable]
    if unreachable:
        problems.append(f"{len(unreachable)} of {len(statuses)} hosts unreachable: {', '.join(unreachable)}")
    failed = [status.name for status in statuses if last_run_failed(status)]
    if failed:
        problems.append(f"{len(failed)} of {len(statuses)} hosts failed in their last run: {', '.join(failed)}")
    return problems


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
