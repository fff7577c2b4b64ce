"""SSH hardening: facts in, commands out; the drop-in's text; the controller's key login;
and the on-host check that keeps a bad sshd configuration from ever going live."""

from __future__ import annotations

import os
import stat
import subprocess
import textwrap
from pathlib import Path

import pytest

from deploy.ssh_hardening import ssh_hardening
from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from roslab import settings
from roslab.ssh.sshd import (
    DROPIN,
    INSTALL_SCRIPT,
    STAGED,
    KeyLogin,
    SshdLoginSettings,
    confirm_key_login,
    dropin_text,
    wanted_settings,
)

HARDENING = "Ensure sshd allows"
RELOAD = "Reload sshd"


def data(tmp_path, **more):
    return host_data(tmp_path, ssh_hostname="10.11.0.2", ssh_key="/keys/teacher", **more)


def test_first_run_logs_in_with_the_key_then_checks_then_installs_then_reloads(tmp_path):
    result = plan(ssh_hardening, FakeUbuntu().facts(), data(tmp_path))
    hardening = result.operation(HARDENING)
    assert hardening.text()[:2] == ["call confirm_key_login", f"upload {STAGED}"]
    assert "roslab-sshd-install /usr/sbin/sshd /etc/ssh/sshd_config " + DROPIN in hardening.text()[2]
    # The key login comes first: it runs on the controller before anything reaches the host.
    login = hardening.commands[0].kwargs["login"]
    assert login == KeyLogin(user="student", address="10.11.0.2", port=22, key="/keys/teacher")
    assert result.operation(RELOAD).text() == ["systemctl try-reload-or-restart ssh.service"]
    dropin = result.uploads()[STAGED]
    assert "PasswordAuthentication no\n" in dropin and "PermitRootLogin no\n" in dropin


def test_second_run_changes_nothing(tmp_path):
    host = FakeUbuntu()
    host.apply(plan(ssh_hardening, host.facts(), data(tmp_path)))
    again = plan(ssh_hardening, host.facts(), data(tmp_path))
    assert again.changing() == {}
    assert again.noops == ["sshd already allows keys only, root login: no"]


def test_a_changed_setting_rewrites_the_dropin(tmp_path):
    host = FakeUbuntu()
    host.apply(plan(ssh_hardening, host.facts(), data(tmp_path)))
    changed = plan(ssh_hardening, host.facts(), data(tmp_path, ssh_password_login=True,
                                                        ssh_permit_root_login="prohibit-password"))
    assert changed.operation(HARDENING).text()[0] == "call confirm_key_login"
    text = changed.uploads()[STAGED]
    assert "PasswordAuthentication yes\nKbdInteractiveAuthentication yes\nPermitRootLogin prohibit-password\n" in text
    host.apply(changed)
    assert plan(ssh_hardening, host.facts(), data(tmp_path, ssh_password_login=True,
                                                  ssh_permit_root_login="prohibit-password")).changing() == {}


def test_diff_shows_the_dropin_change_before_anything_runs(tmp_path, caplog):
    host = FakeUbuntu()
    host.apply(plan(ssh_hardening, host.facts(), data(tmp_path)))
    with caplog.at_level("INFO"):
        plan(ssh_hardening, host.facts(), data(tmp_path, ssh_password_login=True), diff=True)
    printed = "\n".join(record.getMessage() for record in caplog.records)
    assert f"Will modify {DROPIN}" in printed
    assert "- PasswordAuthentication no" in printed and "+ PasswordAuthentication yes" in printed


def test_an_earlier_file_that_overrules_the_dropin_is_not_taken_for_done(tmp_path):
    host = FakeUbuntu()
    host.apply(plan(ssh_hardening, host.facts(), data(tmp_path)))
    facts = host.facts()
    # Our file is in place, but sshd -T says password login is on (a 00-*.conf read before ours).
    facts[SshdLoginSettings] = lambda: {**host._sshd_login_settings(), "effective": {
        **host._sshd_login_settings()["effective"], "passwordauthentication": "yes"}}
    result = plan(ssh_hardening, facts, data(tmp_path))
    # Checked again on the host, where the sshd -T check reports the overruling file.
    assert result.operation(HARDENING).text()[0] == "call confirm_key_login"


def test_switched_off_nothing_is_read_or_changed(tmp_path):
    result = plan(ssh_hardening, {}, data(tmp_path, ssh_hardening_enabled=False))
    assert result.operations == [] and not result.failed


def test_root_as_ssh_user_with_root_login_off_stops_the_host_instead_of_locking_it_out(tmp_path):
    result = plan(ssh_hardening, FakeUbuntu().facts(), data(tmp_path, ssh_user="root", login_user="student"))
    assert result.failed and result.operations == []
    assert "PermitRootLogin no would lock it out" in result.errors[0]
    allowed = plan(ssh_hardening, FakeUbuntu().facts(),
                   data(tmp_path, ssh_user="root", login_user="student", ssh_permit_root_login="prohibit-password"))
    assert not allowed.failed


# The drop-in


def test_dropin_is_managed_sorts_before_cloud_init_and_says_only_what_is_asked():
    text = dropin_text(password_login=False, permit_root_login="no")
    assert text.startswith("# managed by roslab (deploy/ssh_hardening.py)")
    assert Path(DROPIN).name < "50-cloud-init.conf" < "60-cloudimg-settings.conf"
    settings_lines = [line for line in text.splitlines() if line and not line.startswith("#")]
    assert settings_lines == ["PubkeyAuthentication yes", "PasswordAuthentication no",
                              "KbdInteractiveAuthentication no", "PermitRootLogin no"]
    with pytest.raises(ValueError):
        dropin_text(password_login=False, permit_root_login="yes\nPasswordAuthentication yes")


def test_the_setting_refuses_root_login_with_a_password():
    setting = settings.SETTINGS["ssh_permit_root_login"]
    assert settings.check_value(setting, "yes")
    assert settings.check_value(setting, "prohibit-password") is None


def test_the_fact_reads_the_dropin_and_sshds_effective_values():
    output = ["dropin root root 644 abc123", "permitrootlogin without-password",
              "passwordauthentication yes", "PubkeyAuthentication yes"]
    assert SshdLoginSettings().process(output) == {
        "dropin": {"user": "root", "group": "root", "mode": "644", "sha256": "abc123"},
        "effective": {"permitrootlogin": "without-password", "passwordauthentication": "yes",
                      "pubkeyauthentication": "yes"},
    }
    # No drop-in, and sshd's files do not load (a broken student file): pyinfra gives the default.
    assert SshdLoginSettings().process([]) == SshdLoginSettings.default() == {"dropin": None, "effective": {}}


# The controller's key login


def test_key_login_uses_the_key_only_on_a_new_connection_as_roslab_connects():
    login = KeyLogin(user="ubuntu", address="10.0.0.5", port=2222, key="/k/id", known_hosts="/r/known_hosts",
                     strict_host_key_checking="yes")
    argv = login.argv()
    options = {argv[i + 1] for i, word in enumerate(argv) if word == "-o"}
    assert {"BatchMode=yes", "PreferredAuthentications=publickey", "PasswordAuthentication=no",
            "KbdInteractiveAuthentication=no", "ControlPath=none", "IdentitiesOnly=yes",
            "UserKnownHostsFile=/r/known_hosts", "StrictHostKeyChecking=yes"} <= options
    assert argv[-7:] == ["-p", "2222", "-l", "ubuntu", "--", "10.0.0.5", "true"]
    assert argv[argv.index("-i") + 1] == "/k/id"


class RecordingHost:
    def __init__(self):
        self.lines = []

    def log(self, text, log_func=None):
        self.lines.append(text)

    def log_styled(self, text, **kwargs):
        self.lines.append(text)


def test_a_failed_key_login_fails_with_one_line_saying_nothing_changed(monkeypatch):
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(
        a, 255, "", "ubuntu@10.0.0.5: Permission denied (publickey,password).\n"))
    host = RecordingHost()
    assert confirm_key_login(None, host, KeyLogin(user="ubuntu", address="10.0.0.5")) is False
    assert host.lines == [
        "roslab: a key-only SSH login as ubuntu to 10.0.0.5:22 failed (ubuntu@10.0.0.5: Permission "
        "denied (publickey,password).), so ssh hardening changed nothing: sshd keeps its current configuration"
    ]


def test_a_working_key_login_lets_the_change_go_on(monkeypatch):
    ran = []
    monkeypatch.setattr(subprocess, "run", lambda argv, **k: ran.append(argv) or subprocess.CompletedProcess(argv, 0))
    assert confirm_key_login(None, RecordingHost(), KeyLogin(user="ubuntu", address="10.0.0.5")) is True
    assert ran[0][0] == "ssh"


# The on-host check, run for real with a stand-in for sshd


FAKE_SSHD = textwrap.dedent('''\
    #!/usr/bin/env python3
    """Stand-in for sshd -t / sshd -T (unit tests only): Include globs in name order,
    the first value of a keyword wins, an unknown keyword is an error."""
    import glob, sys
    KNOWN = {"include", "pubkeyauthentication", "passwordauthentication",
             "kbdinteractiveauthentication", "permitrootlogin", "hostkey"}
    values = {"pubkeyauthentication": "yes", "passwordauthentication": "yes",
              "kbdinteractiveauthentication": "no", "permitrootlogin": "without-password"}
    seen, errors = set(), []
    def read(path):
        for number, line in enumerate(open(path), 1):
            words = line.split()
            if not words or words[0].startswith("#"):
                continue
            keyword = words[0].lower()
            if keyword == "include":
                for included in sorted(glob.glob(words[1])):
                    read(included)
            elif keyword not in KNOWN:
                errors.append(f"{path} line {number}: Bad configuration option: {words[0]}")
            elif keyword not in seen:
                seen.add(keyword)
                values[keyword] = words[1].lower()
    read(sys.argv[sys.argv.index("-f") + 1])
    if errors:
        print("\\n".join(errors + [f"{sys.argv[sys.argv.index('-f') + 1]}: terminating, "
                                   f"{len(errors)} bad configuration options"]), file=sys.stderr)
        sys.exit(255)
    if "-T" in sys.argv:
        for keyword, value in values.items():
            print(keyword, value)
''')


@pytest.fixture
def sshd_files(tmp_path):
    """/etc/ssh in a temporary directory: Ubuntu's Include line, cloud-init's drop-in, a stand-in sshd."""
    etc = tmp_path / "etc/ssh"
    (etc / "sshd_config.d").mkdir(parents=True)
    (etc / "sshd_config").write_text(f"Include {etc}/sshd_config.d/*.conf\nKbdInteractiveAuthentication no\n")
    (etc / "sshd_config.d/50-cloud-init.conf").write_text("PasswordAuthentication yes\n")
    sshd = tmp_path / "sshd"
    sshd.write_text(FAKE_SSHD)
    sshd.chmod(0o755)
    target = etc / "sshd_config.d" / Path(DROPIN).name
    staged = Path(str(target) + ".roslab-new")
    return sshd, etc / "sshd_config", target, staged


def install(sshd_files, tmp_path, text):
    sshd, config, target, staged = sshd_files
    staged.write_text(text)
    patterns = [f"{k} ({'|'.join(v)})" for k, v in wanted_settings(False, "no").items()]
    return subprocess.run(["sh", "-c", INSTALL_SCRIPT, "roslab-sshd-install", str(sshd), str(config),
                           str(target), str(staged), *patterns],
                          capture_output=True, text=True, env={**os.environ, "TMPDIR": str(tmp_path)})


@pytest.mark.skipif(os.geteuid() != 0, reason="the script gives the drop-in to root")
def test_a_good_dropin_is_moved_into_place_root_owned(sshd_files, tmp_path):
    _, _, target, staged = sshd_files
    result = install(sshd_files, tmp_path, dropin_text(False, "no"))
    assert result.returncode == 0, result.stderr
    assert target.read_text() == dropin_text(False, "no")
    assert stat.S_IMODE(target.stat().st_mode) == 0o644 and target.stat().st_uid == 0
    assert not staged.exists()
    assert not list(tmp_path.glob("roslab-sshd-check.*"))  # the checked copy is gone


def test_a_students_broken_dropin_keeps_ours_out_and_says_why_in_one_line(sshd_files, tmp_path):
    _, _, target, staged = sshd_files
    target.write_text("PasswordAuthentication yes\n")  # the old drop-in, live until now
    broken = target.parent / "99-student.conf"
    broken.write_text("PasswordAuthentcation no\n")
    result = install(sshd_files, tmp_path, dropin_text(False, "no"))
    assert result.returncode != 0
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("roslab: sshd -t rejects the configuration")
    assert f"{broken} line 1: Bad configuration option: PasswordAuthentcation" in result.stderr
    assert target.read_text() == "PasswordAuthentication yes\n"  # unchanged
    assert not staged.exists()
    assert not list(tmp_path.glob("roslab-sshd-check.*"))


def test_a_file_read_before_ours_that_keeps_passwords_is_reported(sshd_files, tmp_path):
    _, _, target, _ = sshd_files
    (target.parent / "00-student.conf").write_text("PasswordAuthentication yes\n")
    result = install(sshd_files, tmp_path, dropin_text(False, "no"))
    assert result.returncode != 0
    assert "sshd would still use 'passwordauthentication yes'" in result.stderr
    assert not target.exists()


def test_a_bad_new_dropin_never_reaches_the_reload(tmp_path):
    """pyinfra runs the reload only if the hardening operation succeeded with changes."""
    result = plan(ssh_hardening, FakeUbuntu().facts(), data(tmp_path))
    reload_op = result.operation(RELOAD)
    condition = reload_op.arguments["_if"]
    assert condition()  # the plan's hardening op succeeded with commands
    hardening_meta = condition.__self__
    hardening_meta._success = False  # as when the on-host check exits 1
    assert not condition()
