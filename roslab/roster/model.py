"""The classroom a valid roster describes: teams, their hosts, and each host's data."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from roslab.checked.problems import Problem
from roslab.host_settings import HostSettings, settings_of, updated

ROLES = ("main", "robot")


@dataclass
class Host:
    name: str
    team: str
    role: str
    address: str
    ubuntu_release: str | None
    distro: str | None
    variant: str | None
    # What pyinfra gets as host data: every deploy setting (defaults merged), the
    # connection keys the roster set, and the roslab_* identity keys.
    data: dict = field(repr=False)
    # Roster line of the host's entry.
    line: int | None = None
    # Roster line where each resolved field was set, for checks' messages.
    lines: dict = field(default_factory=dict, repr=False)
    # Whether roslab gave the host's team a free ROS_DOMAIN_ID from its name (assign_domain_ids).
    domain_assigned: bool = False

    @cached_property
    def settings(self) -> HostSettings:
        """The host's typed settings, what every helper reads (built from `data` on first use, so
        a check of 10,000 hosts builds only those a check asks for; the loader checked `data`)."""
        return settings_of(self.name, self.data)

    @property
    def ros_domain_id(self) -> int | None:
        """The team's domain, as the deploys read it (one value: host data, set from the team)."""
        return self.settings.ros_domain_id

    def set_data(self, **values) -> None:
        """Put what the loader derives after reading the roster (a team's assigned domain, the
        classroom's host lists) into the host's data, and into its typed settings if a check has
        built them already, so both say what pyinfra gets."""
        self.data.update(values)
        if "settings" in self.__dict__:
            self.__dict__["settings"] = updated(self.__dict__["settings"], values)


@dataclass
class Team:
    name: str
    group: str
    ros_domain_id: int | None
    hosts: list[Host]
    # Whether the roster chose the domain (team or classroom), not the default.
    domain_set: bool = True
    # Whether roslab gave the team a free ID from its name (roslab.ros.discovery.assign_domain_ids).
    domain_assigned: bool = False
    line: int | None = None
    domain_line: int | None = None


@dataclass
class Classroom:
    name: str | None
    path: Path
    teams: list[Team]
    warnings: list[Problem] = field(default_factory=list)

    @property
    def hosts(self) -> list[Host]:
        return [host for team in self.teams for host in team.hosts]
