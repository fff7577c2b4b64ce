"""The robot's base computer on its own link (profile `base:`, roslab/profiles/robot_base.py): on a
TurtleBot 4's Pi, usb0 at 192.168.186.3/24, chrony serving time to 192.168.186.0/24, and the
Create 3 at 192.168.186.2 set to the team's domain, namespace and middleware with the Pi as its
NTP server, by the HTTP form POSTs turtlebot4_setup sends (only the Pi reaches the base).

A base that does not answer (unplugged, off, booting, usb0 not up before the first reboot after
the boot config) is said in one line and skipped: the rest of the robot converges, and the next
run configures the base. A firmware of another generation than the distro's is said in one line
too (and in `roslab status`); roslab never flashes the base.
"""

from __future__ import annotations

import json
import posixpath
from io import StringIO

from pyinfra import host, logger
from pyinfra.api import FactBase, deploy, operation
from pyinfra.api.exceptions import OperationValueError
from pyinfra.operations import apt, files, server, systemd

from deploy.common import host_distro, should_run
from roslab import settings
from roslab.host_settings import host_settings
from roslab.quoting import shell_word
from roslab.profiles.robot_base import (
    BASE_PACKAGES,
    POSTED_RECORD,
    RobotBase,
    chrony_text,
    create3_posts,
    create3_wanted,
    firmware_generation,
    firmware_problem,
    netplan_text,
    record_text,
)
from roslab.ros.environment import host_environment

DEFAULTS = settings.defaults("robot_base")
CHRONY_DROP_IN = "/etc/chrony/conf.d/roslab-robot-base.conf"
# How long one request to the base may take (it answers in well under a second when up).
HTTP_TIMEOUT_S = 5


def netplan_path(base: RobotBase) -> str:
    return f"/etc/netplan/61-roslab-{base.interface}.yaml"


class BaseAnswer(FactBase):
    """The base's /api/about answer (None: it did not answer) and what roslab posted last:
    ``{"about": text or None, "posted": {...} or None}``."""

    def command(self, url: str, record: str) -> str:
        return (f"echo '#about'; curl -fsS -m {HTTP_TIMEOUT_S} {shell_word(url + '/api/about')} 2>/dev/null "
                f"|| echo '#no-answer'; echo; echo '#posted'; cat {shell_word(record)} 2>/dev/null || true")

    def process(self, output):
        part: str | None = None
        parts: dict[str, list[str]] = {"about": [], "posted": []}
        for line in output:
            if line.strip() in ("#about", "#posted"):
                part = line.strip()[1:]
            elif part:
                parts[part].append(line)
        about = "\n".join(parts["about"]).strip()
        try:
            posted = json.loads("\n".join(parts["posted"]) or "null")
        except ValueError:
            posted = None
        return {"about": None if about == "#no-answer" or about.endswith("#no-answer") else about,
                "posted": posted if isinstance(posted, dict) else None}


@operation()
def base_settings_kept(base: dict, distro: str, wanted: dict, record: str = POSTED_RECORD):
    """The base holds `wanted` (ROS settings and NTP server): POSTed, then a reboot, when they
    differ from what roslab posted last (the Pi's root-only `record`, written only once every
    POST answered: a failed run posts again next time). A base that does not answer, or runs
    another generation's firmware than the distro's, is said in one line.

    + base: the profile's checked `base:` (roslab/profiles/robot_base.py RobotBase's data)
    + distro: the class's ROS distro (the firmware generation and the namespace follow it)
    + wanted: the form fields (roslab.profiles.robot_base.create3_wanted)
    + record: the Pi's record of the last post
    """
    link = RobotBase.from_data(base)
    if link is None:
        raise OperationValueError("base_settings_kept needs the profile's checked base: mapping")
    url = f"http://{link.base_address}"
    answer = host.get_fact(BaseAnswer, url=url, record=record)
    trouble = base_trouble(link, distro, answer["about"])
    if trouble:
        host.noop(trouble)
    if answer["about"] is None:
        return
    posts = create3_posts(wanted, answer["posted"])
    if not posts:
        host.noop(f"the {link.kind} already has domain {wanted['ros_domain_id']}, namespace "
                  f"{wanted['ros_namespace'] or '/'}, {wanted['rmw_implementation']} and NTP from {link.pi_ip}")
        return
    commands = [f"curl -fsS -m {HTTP_TIMEOUT_S} -o /dev/null -X POST "
                f"{'--data ' + shell_word(body) + ' ' if body else ''}{shell_word(url + path)}" for path, body in posts]
    new = record + ".roslab-new"
    yield (" && ".join(commands) + f" && install -d -m 0755 {shell_word(posixpath.dirname(record))} && umask 077 && "
           f"printf '%s\\n' {shell_word(record_text(wanted))} > {shell_word(new)} && "
           f"mv -f -- {shell_word(new)} {shell_word(record)}")


@deploy("The robot's base is on its link, takes its time from the Pi and runs the team's ROS settings",
        data_defaults=DEFAULTS)
def robot_base():
    """usb0's address (a netplan file, and now when usb0 is up), chrony serving the link, then
    the Create 3's settings over HTTP (only what differs from the last post; a reboot after).

    Reads host_settings(host): robot_base_enabled, roslab_profile (base, name), ros_distro and
    what roslab.ros.environment.host_environment reads (ROS_DOMAIN_ID, RMW_IMPLEMENTATION,
    ROBOT_NAMESPACE from ros_environment).
    """
    typed = host_settings(host)
    resolved = typed.roslab_profile
    base = RobotBase.from_data(resolved.base) if resolved else None
    if base is None or not should_run("robot_base_enabled"):
        return
    link_addressed(base)
    time_served(base)
    base_settings_posted(base, host_distro(), host_environment(typed, host_distro()))


def link_addressed(base: RobotBase) -> None:
    """usb0's netplan file (root-only, as netplan wants), and the address now if usb0 is up."""
    written = files.put(
        name=f"Ensure {netplan_path(base)} gives {base.interface} {base.pi_address} (the link to the {base.kind})",
        src=StringIO(netplan_text(base)), dest=netplan_path(base), user="root", group="root", mode="600")
    interface = shell_word(base.interface)
    # Only this interface, at once (netplan apply would touch every link, the class network too);
    # before the first reboot after the boot config there is no usb0 yet: the file does it at boot.
    server.shell(
        name=f"Ensure {base.interface} holds {base.pi_address} now (when it exists)",
        commands=[f"if ip link show dev {interface} >/dev/null 2>&1; then ip addr replace {shell_word(base.pi_address)} "
                  f"dev {interface} && ip link set {interface} up; fi"],
        _if=written.did_change)


def time_served(base: RobotBase) -> None:
    """chrony installed, with a drop-in that serves the base's network; restarted on a change."""
    apt.packages(name="Ensure chrony is installed (the robot's base takes its time from the Pi)",
                 packages=list(BASE_PACKAGES))
    written = files.put(name=f"Ensure {CHRONY_DROP_IN} lets chrony serve {base.ntp_allow}",
                        src=StringIO(chrony_text(base)), dest=CHRONY_DROP_IN, user="root", group="root",
                        mode="644")
    systemd.service(name="Ensure chrony runs with the drop-in", service="chrony", running=True, restarted=True,
                    _if=written.did_change)


def base_trouble(link: RobotBase, distro: str, about: str | None) -> str | None:
    """What keeps the base's settings from being taken, in one line, from its answer (`about`, None:
    no answer): silent, or another generation's firmware than the distro's; None when neither."""
    if about is None:
        return (f"the {link.kind} at {link.base_address} does not answer on {link.interface} (unplugged, off, or "
                "usb0 not up before the first reboot after the boot config): its settings wait for the next run")
    return firmware_problem(firmware_generation(about), distro, link)


def base_settings_posted(base: RobotBase, distro: str, environment: dict[str, str]) -> None:
    """The base's settings from the team's environment (a middleware it has not: one line). A base
    that does not answer, or runs another distro's firmware, is a warning of the run (one line,
    shown in the compact output; the step itself says it again as its no-op reason)."""
    try:
        wanted = create3_wanted(base, distro, environment)
    except ValueError as error:
        host.noop(f"the {base.kind} keeps its settings: {error}")
        return
    # the step's own fact (same arguments: read once), said here too, where the compact output shows it
    answer = host.get_fact(BaseAnswer, url=f"http://{base.base_address}", record=POSTED_RECORD)
    trouble = base_trouble(base, distro, answer["about"])
    if trouble:
        host.log(f"roslab: robot base: {trouble}", logger.warning)
    base_settings_kept(
        name=f"Ensure the {base.kind} has domain {wanted['ros_domain_id']}, namespace {wanted['ros_namespace'] or '/'}, "
             f"{wanted['rmw_implementation']} and NTP from {base.pi_ip} (posted, then it reboots)",
        base=base.__dict__, distro=distro, wanted=wanted)
