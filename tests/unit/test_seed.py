"""`roslab seed`: first-boot seeds checked by cloud-init's and netplan's own parsers, written once.

cloud-init's schema check and netplan's parser come from Debian's packages, unpacked into
the cache (roslab/seed/tools.py); these tests use the real ones, fetched on first use.
"""

from __future__ import annotations

import os
import shutil
import stat
import struct
import subprocess
import textwrap
from pathlib import Path

import pytest
import yaml

from roslab.ssh import identity
from roslab.cli.main import main
from roslab.seed import targets, tools

PASSWORD = "Pa55: #\"'{x}&*!|>%@`"  # YAML specials in a WPA passphrase
SSID = "\"A\" #1: {x}[y]&*!|>'q' é"  # 26 bytes: an SSID has at most 32
TEACHER = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFlMtlfltx2Ordc++JZrFF/P0U8EAhdPijdaM3K81dM9 teacher \"#1\": x"


def write_roster(tmp_path: Path, host: str = "", classroom: str = "", release: str = "24.04") -> Path:
    roster = tmp_path / "classroom.yaml"
    roster.write_text(textwrap.dedent("""\
        classroom:
          teacher_ssh_keys: [{teacher}]
          ubuntu_release: "{release}"
          timezone: Europe/Berlin
          network_prefix: 24
          network_gateway: 192.168.50.1
          network_nameservers: [192.168.50.1]
        {classroom}
        teams:
          team1:
            hosts:
              team1-main:
                role: main
                address: 192.168.50.11
        {host}
    """).format(teacher=yaml.safe_dump(TEACHER, width=4096).splitlines()[0], release=release,
                classroom=textwrap.indent(classroom, "  "), host=textwrap.indent(host, " " * 8)))
    secrets = tmp_path / "secrets.yaml"
    secrets.write_text(yaml.safe_dump({"classroom_wifi": PASSWORD}))
    secrets.chmod(0o600)
    return roster


NETWORKS = {
    "ethernet-static": "network_address: 192.168.50.11\n",
    "ethernet-dhcp": "network_method: dhcp\n",
    "wifi-static": ("network_address: 192.168.50.11\nnetwork_kind: wifi\nwifi_ssid: {ssid}\n"
                    "wifi_password_secret: classroom_wifi\n"),
    "wifi-dhcp": "network_method: dhcp\nnetwork_kind: wifi\nwifi_ssid: {ssid}\nwifi_password_secret: classroom_wifi\n",
    "untouched": "",
}


def seed(*argv) -> int:
    return main(["seed", *map(str, argv)])


@pytest.mark.parametrize("release", ["24.04", "22.04"])
@pytest.mark.parametrize("network", list(NETWORKS))
def test_seeds_pass_cloud_inits_and_netplans_checks(tmp_path, capsys, release, network):
    host = NETWORKS[network].format(ssid=yaml.safe_dump(SSID, width=4096, allow_unicode=True).splitlines()[0])
    roster = write_roster(tmp_path, host=host, release=release)
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    directory = tmp_path / "seeds" / "team1-main"
    texts = {name: (directory / name).read_text() for name in ("user-data", "network-config", "meta-data")}
    # The same checks roslab seed ran, run again on the files as written.
    assert tools.check_user_data({"team1-main": texts["user-data"]}, []) == {"team1-main": []}
    assert tools.check_network_config("network-config", texts["network-config"], []) == []

    user = yaml.safe_load(texts["user-data"])
    assert texts["user-data"].startswith("#cloud-config\n")
    assert user["hostname"] == "team1-main" and user["timezone"] == "Europe/Berlin"
    assert user["locale"] == "en_US.UTF-8"
    [lab_user] = user["users"]
    assert lab_user["name"] == "ubuntu" and lab_user["lock_passwd"] is True
    assert lab_user["sudo"] == "ALL=(ALL) NOPASSWD:ALL" and lab_user["ssh_authorized_keys"] == [TEACHER]
    assert user["ssh_pwauth"] is False
    keys = identity.host_keys(roster, "team1-main")
    assert user["ssh_keys"] == {"ed25519_private": keys.private_text(), "ed25519_public": keys.public_line()}
    # Nothing fetched from the internet at first boot: no packages, no update, no upgrade.
    assert "packages" not in user and user["package_update"] is False and user["package_upgrade"] is False
    assert user["ntp"]["enabled"] is True

    netplan = yaml.safe_load(texts["network-config"])["network"]
    assert netplan["renderer"] == "networkd"  # without it a Pi falls back to DHCP
    devices = netplan.get("wifis") or netplan["ethernets"]
    config = next(iter(devices.values()))
    if "static" in network:
        assert config["addresses"] == ["192.168.50.11/24"] and config["dhcp4"] is False
    else:
        assert config["dhcp4"] is True
    if "wifi" in network:
        assert config["access-points"] == {SSID: {"password": PASSWORD}}  # exactly, YAML specials and all
    meta = yaml.safe_load(texts["meta-data"])
    assert meta["local-hostname"] == "team1-main" and meta["instance-id"].startswith("roslab-team1-main-")


def test_secrets_stay_in_private_files_and_out_of_output(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["wifi-static"].format(ssid='"lab"'))
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    directory = tmp_path / "seeds" / "team1-main"
    captured = capsys.readouterr()
    # "Pa55" stands for the password however a file escapes the rest of it.
    assert "Pa55" not in captured.out + captured.err
    assert "PRIVATE KEY" not in captured.out + captured.err
    assert "Pa55" not in (directory / "user-data").read_text()
    assert "Pa55" not in (directory / "meta-data").read_text()
    network = yaml.safe_load((directory / "network-config").read_text())["network"]
    assert network["wifis"]["wlan0"]["access-points"]["lab"]["password"] == PASSWORD
    modes = {name: stat.S_IMODE((directory / name).stat().st_mode)
             for name in ("user-data", "network-config", "meta-data")}
    assert modes == {"user-data": 0o600, "network-config": 0o600, "meta-data": 0o644}
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700


def test_a_second_seed_writes_identical_files_and_says_so(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["ethernet-static"])
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    first = {path.name: (path.read_bytes(), path.stat().st_mtime_ns)
             for path in (tmp_path / "seeds/team1-main").iterdir()}
    known = identity.known_hosts_path(roster).read_text()
    capsys.readouterr()
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    assert "team1-main: unchanged" in capsys.readouterr().out
    again = {path.name: (path.read_bytes(), path.stat().st_mtime_ns)
             for path in (tmp_path / "seeds/team1-main").iterdir()}
    assert again == first
    assert identity.known_hosts_path(roster).read_text() == known
    # The seeded key is what strict checking expects at the roster's address.
    assert f"192.168.50.11 {identity.host_keys(roster, 'team1-main').public_line().rsplit(' ', 1)[0]}" in known.replace(
        "team1-main,", "")


def test_seeding_a_pi_whose_other_key_is_recorded_says_it_will_be_refused_until_flashed(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["ethernet-static"])
    identity.trust(roster, "team1-main", ["192.168.50.11"], identity.host_keys(roster, "old-image").public_line())
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    assert "team1-main: its recorded host key is now the seeded one" in capsys.readouterr().out
    seeded = identity.host_keys(roster, "team1-main").public_line()
    assert identity.known_key(roster, "team1-main").key == seeded.split()[1]


def test_a_changed_roster_is_a_new_instance(tmp_path):
    roster = write_roster(tmp_path, host=NETWORKS["ethernet-static"])
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    first = yaml.safe_load((tmp_path / "seeds/team1-main/meta-data").read_text())["instance-id"]
    write_roster(tmp_path, host=NETWORKS["ethernet-dhcp"])
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    assert yaml.safe_load((tmp_path / "seeds/team1-main/meta-data").read_text())["instance-id"] != first


def test_a_roster_error_writes_nothing(tmp_path, capsys):
    roster = write_roster(tmp_path, host="network_adress: 192.168.50.11\n")
    assert seed(roster, "--out", tmp_path / "seeds") == 1
    err = capsys.readouterr().err
    assert "host 'team1-main', field 'network_adress': unknown key" in err
    assert "nothing was written" in err
    assert not (tmp_path / "seeds").exists() and not (tmp_path / ".roslab-state").exists()


def test_a_pi_nobody_could_log_into_is_not_seeded(tmp_path, capsys):
    roster = write_roster(tmp_path)
    teacher = yaml.safe_dump(TEACHER, width=4096).splitlines()[0]
    roster.write_text(roster.read_text().replace(f"teacher_ssh_keys: [{teacher}]", "teacher_ssh_keys: []"))
    assert seed(roster, "--out", tmp_path / "seeds") == 1
    err = capsys.readouterr().err
    assert "host 'team1-main', field 'teacher_ssh_keys': a seeded Pi allows no password login" in err
    assert not (tmp_path / "seeds").exists() and not (tmp_path / ".roslab-state").exists()


def test_the_login_key_and_the_student_account_are_seeded_too(tmp_path):
    key = tmp_path / "id_ed25519"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "controller", "-f", str(key)], check=True)
    roster = write_roster(tmp_path, classroom="ssh_key: id_ed25519\nlogin_user: student\n")
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    users = yaml.safe_load((tmp_path / "seeds/team1-main/user-data").read_text())["users"]
    login_line = (tmp_path / "id_ed25519.pub").read_text().strip()
    assert users[0]["ssh_authorized_keys"] == [TEACHER, login_line]
    assert users[1]["name"] == "student" and "sudo" not in users[1] and "sudo" not in users[1]["groups"]


def test_without_cloud_inits_check_nothing_is_written(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tools, "SYSTEM_PYTHON", str(tmp_path / "no-python3"))
    roster = write_roster(tmp_path, host=NETWORKS["ethernet-static"])
    assert seed(roster, "--out", tmp_path / "seeds") == 1
    assert "cloud-init's check needs Debian's python3" in capsys.readouterr().err
    assert not (tmp_path / "seeds").exists()


def test_cloud_inits_and_netplans_checks_do_refuse_bad_documents():
    problems = tools.check_user_data({"bad": "#cloud-config\nusers: 5\nhostnme: x\n"}, [])["bad"]
    assert any(problem.startswith("users:") for problem in problems)
    assert "hostnme: no cloud-init module reads this key" in problems
    bad_network = "network:\n  version: 2\n  ethernets:\n    eth0:\n      adresses: [10.0.0.2/24]\n"
    [problem, *_] = tools.check_network_config("network-config", bad_network, [])
    assert "network-config:5:" in problem and "unknown key 'adresses'" in problem
    leaky = ("network:\n  version: 2\n  wifis:\n    wlan0:\n      access-points:\n"
             "        x: {password: hunter2-secret, bogus: 1}\n")
    assert all("hunter2-secret" not in line for line in tools.check_network_config("n", leaky, ["hunter2-secret"]))


# --- boot partitions and images -------------------------------------------------------------


def test_a_folder_that_is_not_a_boot_partition_is_refused(tmp_path, capsys):
    roster = write_roster(tmp_path)
    folder = tmp_path / "not-boot"
    folder.mkdir()
    (folder / "user-data").write_text("mine\n")
    assert seed(roster, "--boot-partition", folder, "--limit", "team1-main") == 1
    assert "is not an Ubuntu Raspberry Pi boot partition" in capsys.readouterr().err
    assert sorted(path.name for path in folder.iterdir()) == ["user-data"]
    assert (folder / "user-data").read_text() == "mine\n"


def test_a_boot_partition_gets_the_seed_and_keeps_ubuntus_files(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["ethernet-static"])
    boot = tmp_path / "system-boot"
    boot.mkdir()
    for name, text in {"config.txt": "arm_64bit=1\n", "cmdline.txt": "console=tty1\n",
                       "user-data": "#cloud-config\nubuntu\n", "meta-data": "instance-id: x\n"}.items():
        (boot / name).write_text(text)
    assert seed(roster, "--boot-partition", boot) == 2  # one host: --limit is required
    assert seed(roster, "--boot-partition", boot, "--limit", "team1-main") == 0
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    for name in ("user-data", "network-config", "meta-data"):
        assert (boot / name).read_bytes() == (tmp_path / "seeds/team1-main" / name).read_bytes()
    assert (boot / "user-data.before-roslab").read_text() == "#cloud-config\nubuntu\n"
    capsys.readouterr()
    assert seed(roster, "--boot-partition", boot, "--limit", "team1-main") == 0
    assert "unchanged" in capsys.readouterr().out
    assert (boot / "user-data.before-roslab").read_text() == "#cloud-config\nubuntu\n"


def build_pi_image(path: Path, offset_sectors: int = 2048, size_mb: int = 40) -> int:
    """A raw disk image like Ubuntu's for the Pi: an MBR, one FAT32 partition `system-boot`
    at `offset_sectors` holding config.txt, cmdline.txt and Ubuntu's user-data. Its offset."""
    if not (shutil.which("mkfs.vfat") or Path("/usr/sbin/mkfs.vfat").exists()) or not shutil.which("mcopy"):
        pytest.fail("dosfstools and mtools are needed: run scripts/install-host-tools as root")
    sectors = size_mb * 2048 - offset_sectors
    with open(path, "wb") as image:
        image.truncate(size_mb * 1024 * 1024)
        mbr = bytearray(512)
        mbr[446:462] = struct.pack("<BBBBBBBBII", 0x80, 0, 0, 0, 0x0C, 0, 0, 0, offset_sectors, sectors)
        mbr[510:512] = b"\x55\xaa"
        image.write(mbr)
    mkfs = shutil.which("mkfs.vfat") or "/usr/sbin/mkfs.vfat"
    subprocess.run([mkfs, f"--offset={offset_sectors}", "-F", "32", "-n", "SYSTEM-BOOT", str(path),
                    str(sectors // 2)], check=True, capture_output=True)
    staging = path.parent / "boot-files"
    staging.mkdir()
    for name, text in {"config.txt": "arm_64bit=1\n", "cmdline.txt": "console=tty1\n",
                       "user-data": "#cloud-config\nubuntu default\n"}.items():
        (staging / name).write_text(text)
    env = {**os.environ, "MTOOLS_SKIP_CHECK": "1"}
    subprocess.run(["mcopy", "-i", f"{path}@@{offset_sectors * 512}", *map(str, staging.iterdir()), "::/"],
                   check=True, env=env)
    return offset_sectors * 512


def read_from_image(image: Path, offset: int, name: str) -> bytes:
    out = image.parent / f"read-{name}"
    env = {**os.environ, "MTOOLS_SKIP_CHECK": "1"}
    subprocess.run(["mcopy", "-n", "-i", f"{image}@@{offset}", f"::/{name}", str(out)], check=True, env=env)
    return out.read_bytes()


def test_an_image_gets_the_seed_in_its_boot_partition_without_mounting(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["wifi-static"].format(ssid='"lab"'))
    image = tmp_path / "ubuntu-24.04-preinstalled-server-arm64+raspi.img"
    offset = build_pi_image(image, offset_sectors=8192)
    assert targets.boot_partition(image) == targets.Partition(1, offset, 40 * 1024 * 1024 - offset, "SYSTEM-BOOT")
    assert seed(roster, "--image", image, "--limit", "team1-main") == 0
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    for name in ("user-data", "network-config", "meta-data"):
        assert read_from_image(image, offset, name) == (tmp_path / "seeds/team1-main" / name).read_bytes()
    assert read_from_image(image, offset, "user-data.before-roslab") == b"#cloud-config\nubuntu default\n"
    assert read_from_image(image, offset, "config.txt") == b"arm_64bit=1\n"
    assert stat.S_IMODE(image.stat().st_mode) == 0o600  # it holds a private key and a password now
    out = capsys.readouterr().out
    assert "Pa55" not in out
    before = image.read_bytes()
    assert seed(roster, "--image", image, "--limit", "team1-main") == 0
    assert "team1-main: unchanged" in capsys.readouterr().out
    assert image.read_bytes() == before


def test_an_image_without_a_pi_boot_partition_is_refused(tmp_path, capsys):
    roster = write_roster(tmp_path)
    blank = tmp_path / "blank.img"
    blank.write_bytes(b"\0" * 4096)
    assert seed(roster, "--image", blank, "--limit", "team1-main") == 1
    assert "has no partition table" in capsys.readouterr().err


def test_a_gpt_image_is_read_too(tmp_path):
    """A GPT disk (protective MBR, header at LBA 1): its basic-data FAT partition is found."""
    image = tmp_path / "gpt.img"
    offset = build_pi_image(image, offset_sectors=4096)  # an MBR image, then its table made GPT
    first, last = 4096, 40 * 2048 - 34
    basic_data = bytes.fromhex("A2A0D0EBE5B9334487C068B6B72699C7")  # EBD0A0A2-B9E5-4433-87C0-68B6B72699C7
    with open(image, "r+b") as disk:
        mbr = bytearray(disk.read(512))
        mbr[446:462] = struct.pack("<BBBBBBBBII", 0, 0, 0, 0, 0xEE, 0, 0, 0, 1, 40 * 2048 - 1)
        disk.seek(0)
        disk.write(mbr)
        header = bytearray(92)
        header[:8] = b"EFI PART"
        header[72:88] = struct.pack("<QII", 2, 128, 128)
        disk.seek(512)
        disk.write(header)
        disk.seek(2 * 512)
        disk.write(basic_data + b"\x11" * 16 + struct.pack("<QQ", first, last))
    assert targets.boot_partition(image) == targets.Partition(1, offset, (last - first + 1) * 512, "SYSTEM-BOOT")


def test_the_wifi_regulatory_domain_reaches_netplan_and_passes_its_parser(tmp_path, capsys):
    host = NETWORKS["wifi-static"].format(ssid='"lab"') + "wifi_regulatory_domain: DE\n"
    roster = write_roster(tmp_path, host=host)
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    text = (tmp_path / "seeds/team1-main/network-config").read_text()
    assert tools.check_network_config("network-config", text, []) == []
    assert yaml.safe_load(text)["network"]["wifis"]["wlan0"]["regulatory-domain"] == "DE"
    assert "wifi_regulatory_domain" not in capsys.readouterr().err  # no warning once it is set


def test_wifi_without_a_regulatory_domain_is_warned_about_in_one_line(tmp_path, capsys):
    roster = write_roster(tmp_path, host=NETWORKS["wifi-static"].format(ssid='"lab"'))
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "wifi_regulatory_domain" in line]
    assert len(warnings) == 1 and "team1-main on WiFi without wifi_regulatory_domain" in warnings[0]


@pytest.mark.parametrize("value, message", [
    ("de", "'de' is not a country code like DE, GB or US (did you mean 'DE'?)"),
    ("XX", "'XX' is not a country code like DE, GB or US"),
    ("DEU", "'DEU' is not a country code like DE, GB or US"),
])
def test_a_regulatory_domain_that_is_no_country_code_is_refused_naming_the_field(tmp_path, capsys, value, message):
    roster = write_roster(tmp_path, classroom=f"wifi_regulatory_domain: {value}\n")
    assert seed(roster, "--out", tmp_path / "seeds") == 1
    err = capsys.readouterr().err
    assert "field 'wifi_regulatory_domain'" in err and message in err
    assert not (tmp_path / "seeds").exists()


def test_a_console_password_is_seeded_hashed_never_in_plain_text(tmp_path, capsys):
    roster = write_roster(tmp_path, classroom="console_password_secret: pi_console\n",
                          host=NETWORKS["ethernet-static"])
    secrets = tmp_path / "secrets.yaml"
    secrets.write_text(yaml.safe_dump({"classroom_wifi": PASSWORD, "pi_console": "Cons0le-Pa55 word"}))
    assert seed(roster, "--out", tmp_path / "seeds") == 0
    text = (tmp_path / "seeds/team1-main/user-data").read_text()
    assert "Cons0le" not in text and "Cons0le" not in "".join(capsys.readouterr())
    assert tools.check_user_data({"team1-main": text}, []) == {"team1-main": []}
    [user] = yaml.safe_load(text)["users"]
    assert user["lock_passwd"] is False and yaml.safe_load(text)["ssh_pwauth"] is False
    hashed = user["hashed_passwd"]
    salt = hashed.split("$")[2]
    again = subprocess.run(["openssl", "passwd", "-6", "-salt", salt, "-stdin"], input="Cons0le-Pa55 word\n",
                           capture_output=True, text=True, check=True).stdout.strip()
    assert hashed == again  # the password's SHA-512 crypt hash, as /etc/shadow keeps it
    assert seed(roster, "--out", tmp_path / "seeds") == 0  # the same seed again: the same hash
    assert (tmp_path / "seeds/team1-main/user-data").read_text() == text


def test_a_problem_every_host_shares_is_one_line(tmp_path, capsys):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(textwrap.dedent("""\
        classroom:
          ubuntu_release: "24.04"
        teams:
          team1:
            ros_domain_id: 11
            hosts:
              team1-main: {role: main, address: 192.168.50.11}
              team1-robot: {role: robot, address: 192.168.50.12}
          team2:
            ros_domain_id: 12
            hosts:
              team2-main: {role: main, address: 192.168.50.21}
    """))
    assert seed(roster, "--out", tmp_path / "seeds") == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if "teacher_ssh_keys" in line]
    assert len(lines) == 1, lines
    assert "every host (3), field 'teacher_ssh_keys': a seeded Pi allows no password login" in lines[0]


def test_the_sandbox_reads_a_cards_seed_only_for_the_host_it_was_seeded_for(tmp_path):
    """`roslab sandbox reset HOST --card IMG` boots from the seed on the card's system-boot."""
    from roslab.sandbox.seeding import seed_from_card
    from roslab.sandbox.system import SandboxError

    roster = write_roster(tmp_path, host=NETWORKS["wifi-static"].format(ssid='"lab"'))
    card = tmp_path / "card.img"
    build_pi_image(card)
    with pytest.raises(SandboxError, match="holds no network-config or meta-data: not seeded"):
        seed_from_card(card, "team1-main", tmp_path / "unseeded")  # Ubuntu's own user-data only
    assert seed(roster, "--image", card, "--limit", "team1-main") == 0
    assert seed(roster, "--out", tmp_path / "seeds") == 0

    seed_dir = seed_from_card(card, "team1-main", tmp_path / "read" / "team1-main")

    for name in ("user-data", "network-config", "meta-data"):
        assert (seed_dir / name).read_bytes() == (tmp_path / "seeds/team1-main" / name).read_bytes()
        assert stat.S_IMODE((seed_dir / name).stat().st_mode) == 0o600  # user-data holds a password
    with pytest.raises(SandboxError, match="it was seeded for team1-main, not team1-robot"):
        seed_from_card(card, "team1-robot", tmp_path / "other")
    (tmp_path / "notes.txt").write_text("not a card\n")
    with pytest.raises(SandboxError, match="notes.txt has no partition table"):
        seed_from_card(tmp_path / "notes.txt", "team1-main", tmp_path / "none")
