"""roslab.probe: many facts in one remote command, each value as the fact alone gives it, and
served only until an operation changes the host."""

from __future__ import annotations

import copy
import datetime
import io
import subprocess
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

from fixtures.fake_host import fake_host, plan
from pyinfra import host
from pyinfra.api import FactBase, HiddenValue, StringCommand
from pyinfra.facts.files import Directory, File, FileContents, Sha1File

from roslab import probe
from roslab.ops.files import FileAge
from roslab.ops.files import managed_block
from roslab.ros.workspace import WorkspaceForeign, WorkspaceStamps


class Fails(FactBase):
    def command(self):
        return "echo partial; exit 3"


class NeedsAMissingTool(FactBase):
    def requires_command(self):
        return "roslab-no-such-tool"

    def command(self):
        return "roslab-no-such-tool --list"


def output_lines(command: str) -> list[str]:
    """`command`'s stdout run by sh on this machine, split into lines the way pyinfra's
    connectors split a host's output."""
    stdout = subprocess.run(["sh", "-c", command], capture_output=True, text=True, check=False).stdout
    return [line.rstrip("\n") for line in io.StringIO(stdout)]


def alone(item: probe.Read):
    """The fact's value read on its own, as pyinfra does it (same command, same parser)."""
    fact = item.fact()
    lines = output_lines(probe._section_command(item, fact))
    return fact.process(lines) if lines else fact.default()


def batched(reads: list[probe.Read]) -> dict:
    kept = [(item, item.fact()) for item in reads]
    command = probe.HostProbe().command(
        probe.Commands(probe._section_command(item, fact) for item, fact in kept), "f" * 32)
    return probe.values_of(kept, probe.HostProbe().process(output_lines(command)))


def test_each_batched_value_is_what_the_fact_gives_alone(tmp_path):
    (tmp_path / "lines").write_text("one\ntwo\n")
    (tmp_path / "no-newline").write_text("one\nlast")  # the last line must not merge with the next section
    (tmp_path / "blank-end").write_text("one\n\n")
    (tmp_path / "ws" / ".roslab").mkdir(parents=True)
    (tmp_path / "ws" / ".roslab" / "build.sha256").write_text("abc\n")
    reads = [
        probe.read(FileContents, path=str(tmp_path / "lines")),
        probe.read(FileContents, path=str(tmp_path / "no-newline")),
        probe.read(FileContents, path=str(tmp_path / "blank-end")),
        probe.read(FileContents, path=str(tmp_path / "missing")),
        probe.read(Sha1File, path=str(tmp_path / "lines")),
        probe.read(File, path=str(tmp_path / "lines")),
        probe.read(Directory, path=str(tmp_path / "ws")),
        probe.read(FileAge, path=str(tmp_path / "lines")),
        probe.read(WorkspaceStamps, workspace_dir=str(tmp_path / "ws")),
        # Its command ends with `exit 0` when the workspace is missing: the next read still runs.
        probe.read(WorkspaceForeign, workspace_dir=str(tmp_path / "nothing"), user="root"),
        probe.read(FileContents, path=str(tmp_path / "lines") + " with space"),
    ]
    values = batched(reads)
    assert list(values) == reads
    for item in reads:
        if item.fact is FileAge:  # seconds pass between the two reads on a busy machine
            assert abs(values[item] - alone(item)) <= 2, item
        else:
            assert values[item] == alone(item), item
    assert values[reads[1]] == ["one", "last"] and values[reads[2]] == ["one", ""]


def test_a_read_that_fails_or_lacks_its_tool_is_left_to_the_fact_alone(tmp_path):
    (tmp_path / "lines").write_text("one\n")
    ok = probe.read(FileContents, path=str(tmp_path / "lines"))
    values = batched([probe.read(Fails), ok, probe.read(NeedsAMissingTool)])
    assert values == {ok: ["one"]}


def test_a_file_cannot_forge_the_end_of_its_section(tmp_path):
    forged = tmp_path / "forged"
    forged.write_text(f"{'f' * 32} 1 0\nafter\n")  # the marker of a run that is not this one
    reads = [probe.read(FileContents, path=str(forged)), probe.read(File, path=str(forged))]
    kept = [(item, item.fact()) for item in reads]
    command = probe.HostProbe().command(
        probe.Commands(probe._section_command(item, fact) for item, fact in kept), "0" * 32)
    values = probe.values_of(kept, probe.HostProbe().process(output_lines(command)))
    assert values[reads[0]] == [f"{'f' * 32} 1 0", "after"]
    assert values[reads[1]]["size"] == forged.stat().st_size


def test_pyinfras_log_shows_the_count_of_commands_not_the_shell():
    assert str(probe.Commands(["a", "b"])) == "<2 commands>"


HOSTS = "/etc/hosts"


def test_the_read_is_served_until_an_operation_changes_the_host():
    files = {HOSTS: ["127.0.0.1 localhost"]}

    def deploy():
        probe.read_ahead([probe.read(FileContents, path=HOSTS)])
        first = host.get_fact(FileContents, path=HOSTS)
        first.append("edited by the caller")  # a copy: the read keeps its value
        for text in ("10.0.0.2 pi", "10.0.0.3 pi"):
            managed_block(name=f"block {text}", path=HOSTS, content=text, label="hosts")

    result = plan(deploy, {FileContents: lambda path: files.get(path), File: lambda path: {
        "user": "root", "group": "root", "mode": 644}})
    # Planning both blocks and executing the first read the probe; the second block
    # executes after a change and reads the file from the host (once).
    reads = [name for name in result.facts_asked if name in ("HostProbe", "FileContents")]
    assert reads == ["HostProbe", "FileContents"]
    assert [bool(op.commands) for op in result.operations] == [True, True]


def test_other_arguments_or_connection_arguments_read_from_the_host():
    facts = {FileContents: lambda path, **connection: [path]}
    with fake_host(facts) as (state, pi):
        probe.read_ahead([probe.read(FileContents, path="/a")])
        assert host.get_fact(FileContents, path="/a") == ["/a"]
        assert host.get_fact(FileContents, path="/b") == ["/b"]
        assert host.get_fact(FileContents, path="/a", _sudo=False) == ["/a"]
        assert [name for name, _ in pi.fake_facts.asked] == ["HostProbe", "FileContents", "FileContents"]


class EchoesASecret(FactBase):
    def command(self, secret):
        return StringCommand("echo", HiddenValue(secret))


def test_a_fact_whose_command_holds_a_secret_is_never_batched():
    # The probe's command is logged as one string: a HiddenValue would show there. Nothing
    # is left to batch, so nothing runs (no host is in context here: asking one would raise).
    assert probe.run_probe([probe.read(EchoesASecret, secret="hunter2")]) == {}


def test_a_served_value_is_the_callers_own_copy_at_every_level():
    """What deepcopy gave, for every shape a fact returns: changing it leaves the read alone."""
    when = datetime.datetime(2026, 11, 26, 18, 0)
    read = {
        "packages": {"ros-jazzy-desktop": ["1.0", "1.1"], "sudo": ["1.9"]},
        "file": {"mode": 644, "mtime": when, "size": None, "link": False},
        "lines": ["a", "b"], "groups": {"dialout", "video"}, "pair": ("x", ["y"]),
        "frozen": frozenset({"z"}), "by_default": defaultdict(list, {"k": ["v"]}),
        "data": b"\x00",
    }
    before = copy.deepcopy(read)
    served = probe.own_copy(read)

    assert served == read == copy.deepcopy(read)
    assert type(served["by_default"]) is defaultdict and served["by_default"]["new"] == []
    served["packages"]["ros-jazzy-desktop"].append("2.0")
    served["packages"]["new"] = ["1"]
    served["lines"].append("c")
    served["groups"].add("plugdev")
    served["pair"][1].append("w")
    served["file"]["mode"] = 600
    served["by_default"]["k"].append("w")
    assert read == before


def without_gzip(tmp_path) -> str:
    """A PATH like this machine's, without gzip: a host that cannot pack the probe's output."""
    tools = tmp_path / "bin-without-gzip"
    tools.mkdir()
    for folder in ("/usr/local/bin", "/usr/bin", "/bin"):
        for tool in Path(folder).iterdir():
            if tool.name != "gzip" and not (tools / tool.name).exists():
                (tools / tool.name).symlink_to(tool)
    return str(tools)


def test_the_output_travels_packed_in_one_line_and_unpacks_to_the_plain_sections(tmp_path):
    (tmp_path / "lines").write_text("one\ntwo\n\n")
    (tmp_path / "no-newline").write_text("last")
    reads = [probe.read(FileContents, path=str(tmp_path / "lines")),
             probe.read(FileContents, path=str(tmp_path / "no-newline")),
             probe.read(Fails), probe.read(File, path=str(tmp_path / "lines"))]
    commands = probe.Commands(probe.section(item)[0] for item in reads)
    packed = output_lines(probe.HostProbe().command(commands, "a" * 32))
    plain = output_lines(probe.sections_script(commands, "a" * 32))
    assert len(packed) == 1 and packed[0].startswith(probe.GZIP_BASE64)
    assert len(plain) > 6
    assert probe.unpacked(packed) == plain
    assert probe.HostProbe().process(packed) == probe.HostProbe().process(plain)

    # A host without gzip sends the sections plain; the values are the same.
    env = {"PATH": without_gzip(tmp_path)}
    unpacked = subprocess.run(["/bin/sh", "-c", probe.HostProbe().command(commands, "a" * 32)],
                              capture_output=True, text=True, env=env, check=False).stdout
    assert [line.rstrip("\n") for line in io.StringIO(unpacked)] == plain
    # Output that is not what gzip packed (cut short, say) gives no values: each fact is read alone.
    assert probe.unpacked([packed[0][:40]]) == []
    assert probe.HostProbe().process([packed[0][:40]]) == []


class AsksTheHost(FactBase):
    def command(self):
        return f"uname -r # {host.name}"


def test_a_fact_whose_command_reads_the_host_is_not_read_ahead():
    # Its command differs from host to host; the probe builds each read's command once per run.
    from pyinfra.facts.server import Uptime

    for fact in (AsksTheHost, Uptime):
        with pytest.raises(TypeError, match="reads the host"):
            probe.read(fact)
    assert not probe.asks_the_host(File) and not probe.asks_the_host(FileContents)


def test_each_reads_command_is_built_once_for_every_host(monkeypatch):
    built = []
    command = File.command

    def counted(self, path):
        built.append(path)
        return command(self, path)

    monkeypatch.setattr(File, "command", counted)
    monkeypatch.setattr(probe, "_SECTIONS", {})
    item = probe.read(File, path="/etc/roslab-once")
    first, second = probe.section(item), probe.section(probe.read(File, path="/etc/roslab-once"))
    assert first == second and built == ["/etc/roslab-once"]


@dataclass(frozen=True)
class Entry:
    kind: str
    sha256: str | None = None


@dataclass(frozen=True)
class Holder:
    items: list


def test_a_frozen_value_of_unchangeable_fields_is_served_as_it_is_and_others_are_copied():
    entry = Entry("f", "aa")
    assert probe.own_copy({"a": entry})["a"] is entry
    holder = Holder(["x"])
    served = probe.own_copy(holder)
    assert served == holder and served is not holder and served.items is not holder.items
