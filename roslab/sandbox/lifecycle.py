"""Bring a sandbox classroom up, report on it, reset or reboot its hosts, and take it down.

`up` is idempotent and first clears leftovers of the same instance; `down`
removes everything the instance made (processes, mounts, cgroups, netns,
interfaces, state) and works on a half-broken instance. The machine-wide
pieces (a raised inotify limit, lxcfs) are restored when the last instance goes.
"""

from __future__ import annotations

import json
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from ipaddress import IPv4Network
from pathlib import Path
from typing import Any

import yaml

from roslab.controller_files import file_lock
from roslab.network.state import STATE_DIR
from roslab.ssh import identity

from . import card as card_boot
from . import create3_link, esp32_board, git_standins, hosts, image, seeding, upstream
from .instance import STATE_ROOT, UPSTREAM_PORT, Instance, SandboxHost, releases_by_team
from .system import SandboxError, announced, discard, log, mounts_under, run, sweep_discarded, unmount_all, write_file

DEFAULT_HOSTS = 4
INOTIFY_INSTANCES = Path("/proc/sys/fs/inotify/max_user_instances")
INOTIFY_WANTED = 8192  # the default 128 lets only about 14 hosts boot
MACHINE_DIR = STATE_ROOT / ".machine"  # shared by all instances: lock, saved limits, lxcfs pid


@dataclass(frozen=True)
class Classroom:
    """A running (or half-running) instance and its hosts, as `up` recorded them."""

    instance: Instance
    hosts: list[SandboxHost]
    class_roster: Path | None = None  # `up --roster`: the class's roster its hosts and settings come from

    def host(self, name: str) -> SandboxHost:
        for host in self.hosts:
            if host.name == name:
                return host
        known = ", ".join(host.name for host in self.hosts)
        raise SandboxError(f"sandbox {self.instance.name!r} has no host {name!r} (hosts: {known})")


def _state_file(instance: Instance) -> Path:
    return instance.state_dir / "sandbox.json"


def _instance_lock(instance: Instance) -> Path:
    return STATE_ROOT / ".locks" / f"{instance.name}.lock"


def load(instance: Instance | None = None) -> Classroom:
    """The classroom of a running instance; SandboxError if none is running."""
    instance = instance or Instance.from_env()
    try:
        state = json.loads(_state_file(instance).read_text())
    except FileNotFoundError:
        raise SandboxError(f"no sandbox {instance.name!r} is running: run `roslab sandbox up`") from None
    instance = replace(instance, subnet=IPv4Network(state["subnet"]))
    if state.get("members"):  # brought up from a class's roster: its hosts' names
        return Classroom(instance, instance.plan_members(state["members"], state.get("desktop", ())),
                         Path(state["class_roster"]) if state.get("class_roster") else None)
    return Classroom(instance, instance.plan_hosts(state["hosts"], state.get("desktop", ()),
                                                   state.get("releases")))


def known_hosts(instance: Instance) -> Path:
    """The sandbox classroom's known_hosts: roslab's, beside the sandbox roster."""
    return identity.known_hosts_path(instance.roster_path)


def ssh_argv(instance: Instance, address: str, *command: str, host_name: str | None = None) -> list[str]:
    """An ssh command line reaching a host as the login user with the instance key.

    The host's key is checked strictly against the sandbox's known_hosts; with
    `host_name` it is looked up by the host's name (its line lists the name first),
    so a host that moved to another address is still recognised.
    """
    alias = ["-o", f"HostKeyAlias={host_name}"] if host_name else []
    return [
        "ssh", "-i", str(instance.key_path), "-o", "IdentitiesOnly=yes", "-o", "BatchMode=yes",
        "-o", f"UserKnownHostsFile={known_hosts(instance)}", "-o", "StrictHostKeyChecking=yes",
        "-o", "GlobalKnownHostsFile=/dev/null", *alias, "-o", "LogLevel=ERROR",
        "-o", "ConnectTimeout=5", f"{image.LOGIN_USER}@{address}", *command,
    ]


# -- per-host boot state ----------------------------------------------------------------------
# sandbox.json keeps, per host, how its card was last "flashed": `seeded` (its host key comes
# from roslab's identity store or from a seed, so a plain reset keeps it) and `seed` (the
# host's copy of a NoCloud seed it boots from with cloud-init), `apt_lock_seconds`.

def _host_states(instance: Instance) -> dict[str, dict]:
    return json.loads(_state_file(instance).read_text()).get("boot", {})


def _save_host_states(instance: Instance, states: dict[str, dict]) -> None:
    state = json.loads(_state_file(instance).read_text())
    state["boot"] = states
    write_file(_state_file(instance), json.dumps(state) + "\n")


def _store_boot(instance: Instance, host: SandboxHost) -> hosts.Boot:
    """The host's key from the sandbox roster's identity store (made once, kept across resets)."""
    keys = identity.host_keys(instance.roster_path, host.name)
    return hosts.Boot(host_key=(keys.private_text(), keys.public_line()))


# -- up -------------------------------------------------------------------------------------

def up(count: int | None = None, instance: Instance | None = None, desktop: list[str] | None = None,
       class_roster: Path | None = None) -> Classroom:
    """Boot the instance's classroom (default 4 hosts); a running one is left as it is, except
    that `up --roster` with the roster it runs brings it to that roster as it is now (`_resync`).

    Hosts named in `desktop` emulate Ubuntu Desktop (NetworkManager) instead of Server.
    `class_roster`: the hosts a class's roster names, with its settings where the sandbox can
    serve them (`class_roster.sandbox_roster`; a note is logged for each it cannot).
    """
    instance = instance or Instance.from_env()
    with file_lock(_instance_lock(instance)):
        try:
            running = load(instance)
        except SandboxError:
            running = None
        if class_roster is not None:
            if count is not None:
                raise SandboxError("--hosts and --roster: the roster says which hosts there are")
            class_roster = Path(class_roster).resolve()
            if running is not None and running.class_roster == class_roster and _healthy(running):
                return _resync(running, desktop)  # the class's roster again: the sandbox follows it
            wanted = instance.plan_members(_class_members(class_roster), desktop or ())
        elif running is not None and running.class_roster is not None and count is None and not desktop:
            wanted, class_roster = running.hosts, running.class_roster  # `up` again: what runs
        else:
            wanted = instance.plan_hosts(count or (len(running.hosts) if running else DEFAULT_HOSTS), desktop or ())
        if running and (running.hosts != wanted or running.class_roster != class_roster) and (
                count is not None or desktop or class_roster is not None or running.class_roster is not None):
            raise SandboxError(
                f"sandbox {instance.name!r} is running with other hosts: run `roslab sandbox down` first"
            )
        if running and _healthy(running):
            return running
        _down_locked(instance)  # leftovers of a crashed or half-started run
        try:
            return _up_locked(instance, wanted, class_roster)
        except BaseException:
            _down_locked(instance)
            raise


def _record_ros(instance: Instance, ros: dict[str, str], real_repositories=()) -> None:
    """Keep (in sandbox.json) and say which ROS each distro's archive serves: real or stand-ins,
    and which of the robots' repositories its git upstream serves for real (real_sources.py)."""
    state = json.loads(_state_file(instance).read_text())
    state["ros"] = ros
    state["real_repositories"] = list(real_repositories)
    write_file(_state_file(instance), json.dumps(state) + "\n")
    log.warning("sandbox %r serves ROS 2 %s", instance.name,
                ", ".join(f"{distro}: {what}" for distro, what in sorted(ros.items())))
    standins = [url for _, url, _ in git_standins.repositories(upstream.builtin_repos_files())
                if url not in real_repositories]
    log.warning("sandbox %r serves the robots' repositories: %s", instance.name,
                "; ".join([*(f"{url}: REAL" for url in real_repositories),
                           *(f"{url}: stand-in" for url in dict.fromkeys(standins))]))


def real_repositories(instance: Instance) -> list[str]:
    """The built-in profiles' repositories the running instance serves for real (not stand-ins)."""
    return json.loads(_state_file(instance).read_text()).get("real_repositories", [])


def ros_served(instance: Instance) -> dict[str, str]:
    """distro -> "stand-in" or "real (...)": what the running instance's ROS archive serves."""
    return json.loads(_state_file(instance).read_text()).get("ros", {})


def _healthy(classroom: Classroom) -> bool:
    return all(hosts.is_running(classroom.instance, host.name) for host in classroom.hosts)


def _class_members(path: Path) -> list[dict]:
    """The hosts of the class's roster (checked as every roslab command checks it), noting each
    the sandbox cannot give what the roster asks."""
    from roslab.roster import RosterError, load_roster

    from .class_roster import members

    try:
        classroom = load_roster(path)
    except RosterError as error:
        raise SandboxError(f"--roster {path}: the roster has errors:\n{error}") from None
    found, notes = members(classroom)
    for note in notes:
        log.warning("note: %s", note)
    return found


def _up_locked(instance: Instance, planned: list[SandboxHost], class_roster: Path | None = None) -> Classroom:
    started = time.monotonic()
    classroom = Classroom(instance, planned, class_roster)
    rootfs = image.base_image()
    instance.state_dir.mkdir(parents=True, mode=0o700)
    desktop = [host.name for host in planned if host.flavour == "desktop"]
    write_file(_state_file(instance), json.dumps(
        {"hosts": len(planned), "subnet": str(instance.subnet), "desktop": desktop,
         "releases": list(releases_by_team()),
         **({"members": _members_state(planned), "class_roster": str(class_roster)} if class_roster else {})})
        + "\n")
    _claim_machine(instance)
    run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"roslab-sandbox-{instance.name}",
        "-f", instance.key_path)
    hosts.ensure_bridge(instance)
    with announced("building the stand-in upstream (Ubuntu-layout archive, stand-in ROS packages, rosdep data)"):
        published = upstream.build(instance.state_dir / "upstream", instance.upstream_url, rootfs)
    _record_ros(instance, published.ros or {}, published.real_repositories)
    _update_state(instance, ros_apt_source_sha256=published.ros_apt_source_sha256,  # for _resync's roster
                  snapshot=published.snapshot)
    upstream.start_server(instance.state_dir / "upstream", instance.bridge_address, UPSTREAM_PORT,
                          instance.state_dir / "upstream.pid", instance.state_dir / "upstream.log")
    keyring = upstream.ubuntu_key().keyring.read_bytes()
    write_roster(classroom, published)  # first: the hosts' keys live in the identity store beside it

    with announced(f"booting {len(planned)} hosts and waiting for their SSH"):
        _boot_new(instance, planned, rootfs, keyring)
    _save_host_states(instance, {host.name: {"seeded": True} for host in planned})
    log.info("sandbox %r up: %d hosts in %.1f s", instance.name, len(planned), time.monotonic() - started)
    return classroom


def _boot_new(instance: Instance, planned: list[SandboxHost], rootfs: Path, keyring: bytes) -> None:
    """Wire, mount fresh and boot `planned` (in parallel), then trust their host keys."""
    boots = {host.name: _store_boot(instance, host) for host in planned}

    def boot(host: SandboxHost) -> None:
        hosts.wire_host(instance, host)
        merged = hosts.mount_fresh(instance, host, rootfs)
        hosts.write_host_files(instance, host, merged, keyring, boots[host.name])
        hosts.start(instance, host, merged)
        hosts.wait_for_ssh(host.address)

    _on_all(planned, boot)
    for host in planned:  # one writer: known_hosts is rewritten whole each time
        host_key = boots[host.name].host_key
        assert host_key is not None, f"{host.name}: a host booted with a key here"
        identity.trust(instance.roster_path, host.name, [host.address], host_key[1])


def _members_state(planned: list[SandboxHost]) -> list[dict]:
    return [{"name": host.name, "team": host.team, "role": host.role, "release": host.release,
             "board": host.board, "index": host.index} for host in planned]


def _update_state(instance: Instance, **values) -> dict:
    state = json.loads(_state_file(instance).read_text())
    state.update(values)
    write_file(_state_file(instance), json.dumps(state) + "\n")
    return state


def _resync(running: Classroom, desktop: list[str] | None) -> Classroom:
    """`up --roster ROSTER` while the sandbox of that roster runs: bring it to the roster as it
    is now. Hosts the roster no longer names are stopped and removed, new ones (or ones whose
    team, role, release or desktop flavour changed: re-flashed) booted on free addresses, every
    other host kept as it is (converged, at its address); the sandbox's roster is written anew
    from the class's, and what changed is said."""
    instance, class_roster = running.instance, running.class_roster
    state = json.loads(_state_file(instance).read_text())
    if "ros_apt_source_sha256" not in state:
        raise SandboxError(f"sandbox {instance.name!r} was brought up by an older roslab: "
                           "run `roslab sandbox down` first")
    if class_roster is None:  # up --roster is what resyncs
        raise SandboxError(f"sandbox {instance.name!r} was not brought up from a class roster")
    members = _class_members(class_roster)
    desktop_names = set(desktop) if desktop else {host.name for host in running.hosts if host.flavour == "desktop"}
    old = {host.name: host for host in running.hosts}
    kept = {}
    for member in members:
        host = old.get(member["name"])
        flavour = "desktop" if member["name"] in desktop_names else "server"
        if host and (host.team, host.role, host.release, host.flavour) == (
                member["team"], member["role"], member["release"], flavour):
            kept[host.name] = host.index
    free = iter(sorted(set(range(len(members) + len(old))) - set(kept.values())))
    planned = instance.plan_members([{**member, "index": kept.get(member["name"]) if member["name"] in kept
                                      else next(free)} for member in members],
                                    [name for name in desktop_names if any(m["name"] == name for m in members)])
    added = [host for host in planned if host.name not in kept]
    removed = [host for host in running.hosts if host.name not in kept]
    classroom = Classroom(instance, planned, class_roster)
    before = instance.roster_path.read_text() if instance.roster_path.exists() else ""
    published = upstream.Upstream(instance.upstream_url, state["ros_apt_source_sha256"], state.get("ros"),
                                  tuple(state.get("real_repositories", ())), state.get("snapshot", ""))
    write_roster(classroom, published)  # checked before any host changes
    for host in removed:
        _remove_host(instance, host)
    _update_state(instance, hosts=len(planned), members=_members_state(planned),
                  desktop=sorted(host.name for host in planned if host.flavour == "desktop"))
    if added:
        with announced(f"booting {len(added)} new hosts and waiting for their SSH"):
            _boot_new(instance, added, image.base_image(), upstream.ubuntu_key().keyring.read_bytes())
        states = _host_states(instance)
        states.update({host.name: {"seeded": True} for host in added})
        _save_host_states(instance, states)
    for line in roster_changes(before, instance.roster_path.read_text(), added, removed):
        log.warning("sandbox %r: %s", instance.name, line)
    return classroom


def _remove_host(instance: Instance, host: SandboxHost) -> None:
    """Stop a host the roster no longer names and remove its disk and network."""
    hosts.stop(instance, host.name)
    unmount_all(instance.host_dir(host))
    discard(instance.host_dir(host), STATE_ROOT)
    run("ip", "netns", "delete", instance.netns(host), check=False)  # its veth end goes with it
    run("ip", "link", "delete", instance.veth(host), check=False)


# Roster keys whose values are never printed (a WiFi password in the class's roster).
_SECRET_WORDS = ("password", "psk", "secret", "passphrase", "token")


def roster_changes(before: str, after: str, added: list[SandboxHost], removed: list[SandboxHost]) -> list[str]:
    """What `up --roster` changed, one line each: hosts removed and added, then each roster
    setting that changed (its path, old -> new; a secret's value is not shown)."""
    lines = [f"removed {host.name} (no longer in the roster)" for host in removed]
    lines += [f"added {host.name} ({host.team} {host.role}, Ubuntu {host.release}, {host.address})" for host in added]
    before_data, after_data = yaml.safe_load(before) or {}, yaml.safe_load(after) or {}
    old, new = _flatten(before_data), _flatten(after_data)
    old_teams, new_teams = set(before_data.get("teams") or ()), set(after_data.get("teams") or ())
    lines += [f"removed team {team}" for team in sorted(old_teams - new_teams)]
    lines += [f"added team {team}" for team in sorted(new_teams - old_teams)]
    # A team or host that came or went is its one line, not one line per setting.
    whole = [f"teams.{team}." for team in old_teams ^ new_teams]
    whole += [f".hosts.{host.name}." for host in [*removed, *added]]
    for path in sorted(old.keys() | new.keys()):
        if any(part in f".{path}." for part in whole) or old.get(path) == new.get(path):
            continue
        secret = any(word in path.lower() for word in _SECRET_WORDS)
        show = (lambda value: "(hidden)" if secret and value is not None else
                "(unset)" if value is None else json.dumps(value))
        lines.append(f"setting {path}: {show(old.get(path))} -> {show(new.get(path))}")
    return lines or ["the roster is unchanged: nothing to do"]


def _flatten(value, prefix: str = "") -> dict[str, object]:
    if isinstance(value, dict) and value:
        flat: dict[str, object] = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: value}


def _on_all(targets: list[SandboxHost], action) -> None:
    with ThreadPoolExecutor(max_workers=min(16, len(targets))) as pool:
        for future in [pool.submit(action, host) for host in targets]:
            future.result()


def roster(classroom: Classroom, published: upstream.Upstream) -> dict:
    """The roster `up` writes: a real roster whose settings point at the sandbox upstream."""
    instance = classroom.instance
    teams: dict[str, dict] = {}
    for host in classroom.hosts:
        number = host.team.removeprefix("team")
        team = teams.setdefault(host.team, {
            "ubuntu_release": host.release,
            # team1: 11, team2: 12...; a class's own team names (up --roster) keep the class's IDs
            **({"ros_domain_id": 10 + int(number)} if number.isdigit() else {}),
            "hosts": {},
        })
        team["hosts"][host.name] = {"role": host.role, "address": host.address,
                                    **({"board": host.board} if host.board else {})}
    return {
        "classroom": {
            "name": f"sandbox-{instance.name}",
            "ssh_user": image.LOGIN_USER,
            "ssh_key": str(instance.key_path),
            # Named explicitly so that copies of this roster elsewhere (as tests make)
            # still check the sandbox hosts' keys strictly against the sandbox's store.
            "ssh_known_hosts_file": str(known_hosts(instance)),
            "ssh_strict_host_key_checking": "yes",
            **published.roster_settings(),
        },
        "teams": teams,
    }


def write_roster(classroom: Classroom, published: upstream.Upstream) -> None:
    instance = classroom.instance
    header = (f"# Roster of the roslab sandbox {instance.name!r}, written by `roslab sandbox up`\n"
              "# and removed by `roslab sandbox down`. Its settings point at the sandbox's local\n"
              "# upstream exactly as a real classroom's would point at a mirror.\n")
    written = roster(classroom, published)
    key_file = instance.state_dir / "ros-archive-key.asc"  # first: a roster in snapshot mode names it
    write_file(key_file, upstream.ros_key().armored.read_bytes())
    if classroom.class_roster is not None:
        from .class_roster import sandbox_roster

        written, notes = sandbox_roster(classroom.class_roster, written,
                                        {host.name: host.address for host in classroom.hosts},
                                        {host.name: host.release for host in classroom.hosts},
                                        snapshot=published.snapshot_settings(key_file))
        header += f"# Its hosts and settings are the class's in {classroom.class_roster} (`up --roster`).\n"
        for note in notes:
            log.warning("note: %s", note)
    write_file(instance.roster_path, header + yaml.safe_dump(written, sort_keys=False))
    if classroom.class_roster is not None:
        from roslab.roster import RosterError, load_roster

        try:  # before any host boots: a class setting the sandbox cannot take is named here
            load_roster(instance.roster_path)
        except RosterError as error:
            raise SandboxError(f"the sandbox's copy of {classroom.class_roster} has errors:\n{error}") from None
    write_file(instance.state_dir / "upstream.yaml",
               "# Settings for the ROS apt source's mirror mode (ros_apt_source_mode: mirror)\n"
               "# and its snapshot mode (ros_apt_source_mode: snapshot, the stand-in snapshot server).\n"
               + yaml.safe_dump({**published.mirror_settings(key_file), **published.snapshot_settings(key_file)},
                                sort_keys=False))


# -- machine-wide resources ----------------------------------------------------------------

def _claim_machine(instance: Instance) -> None:
    with file_lock(MACHINE_DIR / "lock"):
        saved = MACHINE_DIR / "inotify-max-user-instances"
        current = int(INOTIFY_INSTANCES.read_text())
        if current < INOTIFY_WANTED:
            if not saved.exists():
                write_file(saved, f"{current}\n")
            INOTIFY_INSTANCES.write_text(f"{INOTIFY_WANTED}\n")
        if hosts.start_lxcfs(MACHINE_DIR / "lxcfs.pid", MACHINE_DIR / "lxcfs.log"):
            write_file(MACHINE_DIR / "lxcfs.ours", "")


def _release_machine() -> None:
    with file_lock(MACHINE_DIR / "lock"):
        others = [path for path in STATE_ROOT.iterdir() if not path.name.startswith(".")]
        if others:
            return
        saved = MACHINE_DIR / "inotify-max-user-instances"
        if saved.exists():
            INOTIFY_INSTANCES.write_text(saved.read_text())
            saved.unlink()
        if (MACHINE_DIR / "lxcfs.ours").exists():
            hosts.stop_lxcfs(MACHINE_DIR / "lxcfs.pid", MACHINE_DIR / "lxcfs.log")
            (MACHINE_DIR / "lxcfs.ours").unlink()


# -- down -------------------------------------------------------------------------------------

def down(instance: Instance | None = None) -> None:
    """Stop and remove everything the instance made; safe to run on anything left over."""
    instance = instance or Instance.from_env()
    sweep_discarded(STATE_ROOT)  # what an earlier down could not finish deleting (a reboot)
    with file_lock(_instance_lock(instance)):
        _down_locked(instance)
    _release_machine()
    _instance_lock(instance).unlink(missing_ok=True)


def _down_locked(instance: Instance) -> None:
    if not instance.state_dir.exists() and not any(cgroup.is_dir() for cgroup in hosts.instance_cgroups(instance)):
        hosts.remove_network(instance)  # nothing else is there: quietly
        return
    with announced(f"taking sandbox {instance.name!r} down (stopping its hosts, unmounting, removing its network)"):
        for cgroup in hosts.instance_cgroups(instance):
            hosts.kill_cgroup_trees([cgroup])
            try:
                cgroup.parent.rmdir()  # .../roslab, when no other instance uses it
            except OSError:
                pass
        upstream.stop_server(instance.state_dir / "upstream.pid")
        esp32_board.stop_all(instance.state_dir)  # `roslab sandbox board` processes, on this machine
        create3_link.unplug_all(instance)  # `roslab sandbox create3` stand-ins (their netns go below)
        for host_dir in sorted((instance.state_dir / "hosts").glob("*/")):
            card_boot.release(host_dir)  # a card's system-boot written back before it is let go
        if instance.state_dir.exists():
            unmount_all(instance.state_dir)
        hosts.remove_network(instance)
        # Gone at once; its files (a converged host's overlay: ~557 MB) are deleted in the background.
        discard(instance.state_dir, STATE_ROOT)


# -- status, reset, reboot -------------------------------------------------------------------

def status(instance: Instance | None = None) -> dict:
    """What is running: per host its address, release and whether it runs and offers SSH."""
    classroom = load(instance)
    report: dict[str, Any] = {"name": classroom.instance.name, "subnet": str(classroom.instance.subnet),
              "upstream": classroom.instance.upstream_url, "roster": str(classroom.instance.roster_path),
              "ros": ros_served(classroom.instance), "hosts": []}
    for host in classroom.hosts:
        running = hosts.is_running(classroom.instance, host.name)
        try:
            ssh = running and hosts.wait_for_ssh(host.address, timeout=0.5) is not None
        except SandboxError:
            ssh = False
        report["hosts"].append({"name": host.name, "address": host.address, "release": host.release,
                                "flavour": host.flavour,
                                "team": host.team, "role": host.role, "running": running, "ssh": ssh})
    return report


def reset(host_names: list[str] | str, instance: Instance | None = None, *, unseeded: bool = False,
          seed: Path | None = None, apt_lock_seconds: float | None = None, card: Path | None = None) -> float:
    """Re-flash hosts: a fresh image (their changes are lost), booted; return the seconds taken.

    Like a Pi's SD card written again, the host's SSH host key survives only if the card
    was seeded: a host made by `up` keeps its key from the sandbox roster's identity store,
    a host re-flashed with `seed` boots from that seed again. Otherwise, and always with
    `unseeded`, it makes a new random key that roslab does not know (the host then no
    longer counts as seeded). With `seed` (one host) it boots "as flashed": cloud-init
    runs on the NoCloud seed presented as the boot partition, and a stand-in for
    first-boot unattended-upgrades holds the dpkg lock `apt_lock_seconds` (default 20).
    With `card` too (the card `seed` was read off), the host boots from the card itself:
    its `writable` is the host's root, its system-boot the boot partition (card.py); a later
    reset without it lets the card go and boots the sandbox's image with the card's seed.
    """
    started = time.monotonic()
    classroom = load(instance)
    names = [host_names] if isinstance(host_names, str) else list(host_names)
    targets = [classroom.host(name) for name in names]
    instance = classroom.instance
    _check_reset(instance, targets, unseeded=unseeded, seed=seed, apt_lock_seconds=apt_lock_seconds, card=card)
    if card is not None:  # refused before the host is stopped
        card_boot.check(instance.host_dir(targets[0]), card, targets[0].release, targets[0].name)
    rootfs = image.base_image()
    keyring = upstream.ubuntu_key().keyring.read_bytes()

    with file_lock(_instance_lock(instance)):
        states = _host_states(instance)

        def boot_for(host: SandboxHost) -> hosts.Boot:
            seed_copy = hosts.keep_seed(instance, host, Path(seed)) if seed is not None else None
            state = states[host.name] = reflash_state(states.get(host.name, {}), seed_copy=seed_copy,
                                                      unseeded=unseeded, apt_lock_seconds=apt_lock_seconds,
                                                      card=card)
            if state["seed"]:
                return hosts.Boot(seed=Path(state["seed"]), apt_lock_seconds=state["apt_lock_seconds"],
                                  card=Path(state["card"]) if state["card"] else None)
            if state["seeded"]:
                return _store_boot(instance, host)
            return hosts.Boot(host_key=hosts.random_host_key(instance, host))

        boots = {host.name: boot_for(host) for host in targets}

        try:
            _on_all(targets, lambda host: _boot_reflashed(instance, host, boots[host.name], rootfs, keyring))
        finally:
            _save_host_states(instance, states)
    return time.monotonic() - started


def _check_reset(instance: Instance, targets: list[SandboxHost], *, unseeded: bool, seed: Path | None,
                 apt_lock_seconds: float | None, card: Path | None) -> None:
    """SandboxError, before any host is touched, for a reset that cannot be done as asked."""
    if card is not None and seed is None:
        raise SandboxError("reset: a card is booted with the seed read off it")
    if seed is not None:
        if unseeded:
            raise SandboxError("reset: --seed and --unseeded exclude each other")
        if len(targets) != 1:
            raise SandboxError("reset --seed: a seed is one host's: name exactly one HOST")
        seeding.seed_address(Path(seed), instance.subnet)
    if apt_lock_seconds is not None:
        seeding.check_apt_lock_seconds(apt_lock_seconds)


def _boot_reflashed(instance: Instance, host: SandboxHost, boot: hosts.Boot, rootfs: Path, keyring: bytes) -> None:
    """Stop the host, give it its new disk (a fresh overlay, or its card) and boot it; wait for SSH."""
    hosts.stop(instance, host.name)
    if boot.card:  # the card's own partitions: the seed is on its system-boot
        merged, boot_partition = card_boot.mount(instance.host_dir(host), boot.card, host.release, host.name)
        boot = replace(boot, seed=boot_partition)
    else:
        merged = hosts.mount_fresh(instance, host, rootfs)
    hosts.write_host_files(instance, host, merged, keyring, boot)
    hosts.start(instance, host, merged, boot.seed, card=boot.card is not None)
    if boot.seed:  # at the seed's address, after cloud-init's first stages (docs/sandbox.md)
        hosts.wait_for_ssh(seeding.seed_address(boot.seed, instance.subnet), timeout=180)
    else:
        hosts.wait_for_ssh(host.address)


def reflash_state(state: dict, *, seed_copy: Path | None = None, unseeded: bool = False,
                  apt_lock_seconds: float | None = None, card: Path | None = None) -> dict:
    """A host's boot state after a re-flash: a seed makes it seeded (and boots from it from
    now on), `unseeded` makes it unseeded; a plain re-flash keeps what it was. It boots from
    `card` only when this re-flash names one: any other lets the card go."""
    state = {"seeded": False, "seed": None, "apt_lock_seconds": seeding.FIRST_BOOT_APT_LOCK_SECONDS, **state,
             "card": str(card) if card else None}
    if seed_copy is not None:
        state.update(seeded=True, seed=str(seed_copy))
    elif unseeded:
        state.update(seeded=False, seed=None)
    if apt_lock_seconds is not None:
        state["apt_lock_seconds"] = apt_lock_seconds
    return state


def boots_from_card(host_name: str, instance: Instance | None = None) -> bool:
    """Whether the host runs on a card's own partitions (`reset --card` of a sandbox card)."""
    classroom = load(instance)
    return bool(_host_states(classroom.instance).get(classroom.host(host_name).name, {}).get("card"))


def _boot_partition(instance: Instance, host: SandboxHost) -> tuple[Path | None, bool]:
    """(what the host has at /boot/firmware, whether it is a card's) when booted from its disk as
    it is: its card's system-boot (still mounted), its seed, or nothing."""
    state = _host_states(instance).get(host.name, {})
    if state.get("card"):
        return card_boot.boot_folder(instance.host_dir(host)), True
    return (Path(state["seed"]) if state.get("seed") else None), False


def reboot(host_name: str, instance: Instance | None = None, timeout: float = 60.0) -> float:
    """Reboot a host the way `reboot` inside does; return the seconds until SSH is back."""
    started = time.monotonic()
    classroom = load(instance)
    host = classroom.host(host_name)
    old_init = hosts.container_init_pid(classroom.instance, host.name)
    hosts.request_reboot(classroom.instance, host.name)
    deadline = started + timeout
    while time.monotonic() < deadline:  # a new PID 1 means the reboot happened
        pid = hosts.container_init_pid(classroom.instance, host.name)
        if pid is not None and pid != old_init:
            break
        time.sleep(0.05)
    else:
        raise SandboxError(f"host {host_name!r} did not reboot within {timeout:.0f} s")
    hosts.wait_for_ssh(host.address, timeout=max(1.0, deadline - time.monotonic()))
    return time.monotonic() - started


def power_cut(host_name: str, instance: Instance | None = None) -> None:
    """Cut a host's power: every process in it killed at once, no shutdown. Its disk stays
    as it was (what was written survives, as on a Pi's SD card); `power_on` boots it again."""
    classroom = load(instance)
    host = classroom.host(host_name)
    hosts.stop(classroom.instance, host.name)


def power_on(host_name: str, instance: Instance | None = None, wait_at: str | None = None,
             timeout: float = 120.0) -> float:
    """Boot a host whose power was cut, from its disk as it was; wait until sshd answers at
    `wait_at` (default: its roster address); return the seconds taken."""
    started = time.monotonic()
    classroom = load(instance)
    host = classroom.host(host_name)
    if hosts.is_running(classroom.instance, host.name):
        raise SandboxError(f"host {host_name!r} of sandbox {classroom.instance.name!r} is running")
    merged = classroom.instance.host_dir(host) / "merged"
    if not mounts_under(merged.parent) or not (merged / "etc").is_dir():
        raise SandboxError(f"host {host_name!r} has no disk to boot from: `roslab sandbox reset` it")
    # A Pi's network card starts empty and down after a power cut; the host's netns outlives
    # its processes here, so its addresses and routes go as the power would take them, and the
    # link goes down: networkd brings it up, and the kernel gives it its IPv6 link-local address
    # again (flushed with the others; without it networkd waits, "configuring", and
    # network-online.target with it, for wait-online's 2 minutes).
    netns = classroom.instance.netns(host)
    run("ip", "-n", netns, "address", "flush", "dev", "eth0", check=False)
    run("ip", "-n", netns, "route", "flush", "dev", "eth0", check=False)
    run("ip", "-n", netns, "link", "set", "dev", "eth0", "down", check=False)
    hosts.start(classroom.instance, host, merged, *_boot_partition(classroom.instance, host))
    hosts.wait_for_ssh(wait_at or host.address, timeout=timeout)
    return time.monotonic() - started


def ssh(host_name: str, command: list[str], instance: Instance | None = None) -> None:
    """Replace this process with ssh to the host (interactive when no command)."""
    classroom = load(instance)
    argv = ssh_argv(classroom.instance, classroom.host(host_name).address, *command, host_name=host_name)
    os.execvp(argv[0], argv)


# -- saved states ----------------------------------------------------------------------------
# `save NAME` keeps each host's disk changes (its overlay's upper directory, copied with owners,
# modes and xattrs, so overlay whiteouts too) and roslab's run records beside the sandbox roster
# under the instance's folder (`down` removes them). `restore NAME` lays the saved layer read-only
# under a fresh, empty upper directory: seconds, not a converge, and the saved state stays as it
# was for the next restore. Same instance, same subnet: every address and key is the saved one.

SAVED_DIR = "saved"
_SAVE_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9._-]{0,39}$")


def saved_path(instance: Instance, name: str) -> Path:
    """Where the saved state NAME of the instance lives; SandboxError for a name that is no name."""
    if not _SAVE_NAME_RE.match(name) or ".." in name:
        raise SandboxError(f"saved state name {name!r} is invalid: use 1-40 lowercase letters, digits, "
                           "'.', '_' and '-', starting with a letter or digit")
    return instance.state_dir / SAVED_DIR / name


def saved_names(instance: Instance) -> list[str]:
    """The states saved on the instance, by name."""
    folder = instance.state_dir / SAVED_DIR
    return sorted(path.name for path in folder.iterdir() if (path / "saved.json").is_file()) \
        if folder.is_dir() else []


def saved_record(classroom: Classroom, states: dict[str, dict], host_layers: dict[str, list[str]]) -> dict:
    """What saved.json says of a saved state: its hosts as they were (name, address) with their
    boot states and the saved layers each lay on."""
    return {"subnet": str(classroom.instance.subnet),
            "hosts": {host.name: {"address": host.address, "boot": states.get(host.name, {}),
                                  "layers": host_layers.get(host.name, [])} for host in classroom.hosts}}


def check_restorable(record: dict, classroom: Classroom, name: str) -> None:
    """Refuse a saved state whose hosts are not the running ones at the same addresses."""
    saved = {host: values["address"] for host, values in record["hosts"].items()}
    running = {host.name: host.address for host in classroom.hosts}
    if record["subnet"] != str(classroom.instance.subnet) or saved != running:
        raise SandboxError(f"saved state {name!r} of sandbox {classroom.instance.name!r} holds other hosts "
                           f"({', '.join(f'{h} {a}' for h, a in sorted(saved.items()))}) than run now: "
                           "restore it on the classroom it was saved from")


def save(name: str, instance: Instance | None = None) -> float:
    """Save every host's disk (stopped for the copy, booted again if it ran) and roslab's run
    records beside the sandbox roster as NAME; return the seconds taken."""
    started = time.monotonic()
    classroom = load(instance)
    instance = classroom.instance
    target = saved_path(instance, name)
    with file_lock(_instance_lock(instance)):
        if target.exists():
            raise SandboxError(f"sandbox {instance.name!r} already has a saved state {name!r}: choose another name "
                               f"(saved: {', '.join(saved_names(instance))})")
        on_cards = sorted(host for host, state in _host_states(instance).items() if state.get("card"))
        if on_cards:
            raise SandboxError(f"{', '.join(on_cards)} run on a card (`reset --card`): a saved state holds "
                               "hosts' overlays, not cards; `roslab sandbox reset` them first")
        partial = target.with_name(f".{name}.partial")
        discard(partial, STATE_ROOT)
        layers = {}

        def keep(host: SandboxHost) -> None:
            running = hosts.is_running(instance, host.name)
            hosts.stop(instance, host.name)
            layers[host.name] = [str(path) for path in hosts.host_layers(instance, host)]
            copy_tree(instance.host_dir(host) / "upper", partial / "hosts" / host.name)
            if running:
                _boot_disk(classroom, host)

        _on_all(classroom.hosts, keep)
        controller = instance.roster_path.parent / STATE_DIR
        if controller.is_dir():
            copy_tree(controller, partial / "controller")
        write_file(partial / "saved.json", json.dumps(saved_record(classroom, _host_states(instance), layers)) + "\n")
        os.rename(partial, target)
    return time.monotonic() - started


def restore(name: str, instance: Instance | None = None) -> float:
    """Bring every host back to the saved state NAME (its disk, its boot state) and roslab's run
    records beside the sandbox roster with it; return the seconds until every host offers SSH."""
    started = time.monotonic()
    classroom = load(instance)
    instance = classroom.instance
    source = saved_path(instance, name)
    with file_lock(_instance_lock(instance)):
        try:
            record = json.loads((source / "saved.json").read_text())
        except FileNotFoundError:
            raise SandboxError(f"sandbox {instance.name!r} has no saved state {name!r} "
                               f"(saved: {', '.join(saved_names(instance)) or 'none'})") from None
        check_restorable(record, classroom, name)
        rootfs = image.base_image()
        _save_host_states(instance, {host: values["boot"] for host, values in record["hosts"].items()})

        def back(host: SandboxHost) -> None:
            hosts.stop(instance, host.name)
            layers = [source / "hosts" / host.name, *map(Path, record["hosts"][host.name]["layers"])]
            hosts.mount_fresh(instance, host, rootfs, layers)
            _boot_disk(classroom, host)

        _on_all(classroom.hosts, back)
        controller = instance.roster_path.parent / STATE_DIR
        discard(controller, STATE_ROOT)
        if (source / "controller").is_dir():
            copy_tree(source / "controller", controller)
    return time.monotonic() - started


def copy_tree(source: Path, target: Path) -> None:
    """A copy of a directory keeping owners, modes, times, xattrs and device nodes (overlay whiteouts)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    run("cp", "-a", "--reflink=auto", "--", source, target)


def _boot_disk(classroom: Classroom, host: SandboxHost, timeout: float = 120.0) -> None:
    """Boot a stopped host from its disk as it is and wait for its SSH (at its seed's address
    when it boots from a seed and cloud-init has not yet moved it)."""
    instance = classroom.instance
    # The host's netns and its eth0 stay as they are, as for a reset: a flush would also take
    # the IPv6 link-local address the kernel gives only when the link comes up, and networkd
    # would wait for it ("configuring"), holding network-online.target and the nodes' service.
    hosts.start(instance, host, instance.host_dir(host) / "merged", *_boot_partition(instance, host))
    hosts.wait_for_ssh(host.address, timeout=timeout)
