"""cloud-init's and netplan's own checks of a seed, from Debian's packages, never installed.

Installing Debian's cloud-init on the controller would enable its services on this
machine at the next boot, so its .deb (and netplan's) is fetched with `apt-get download`
and unpacked with `dpkg-deb -x` into `$ROSLAB_CACHE_DIR/seed-tools/` (default
/var/cache/roslab), once, under a file lock. Then:

- user-data: cloud-init's schema check (`validate_cloudconfig_schema`, strict) run by the
  system python3 with the Debian python modules cloud-init imports
  (`scripts/install-host-tools` installs them), plus a check that every top-level key
  is one a cloud-init module reads (22.4's schema allows any);
- network-config: cloud-init 22.4 has no schema for it; on a Pi cloud-init hands a
  version 2 network-config to netplan as it is, so netplan's own parser checks it
  (`netplan generate --root-dir`, the unpacked binary and its library).

If either tool is missing or cannot run, `roslab seed` stops with `SeedToolError`: a
seed is never written unchecked.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from roslab.network.render import mask_secrets

PACKAGES = ("cloud-init", "netplan.io", "libnetplan0")
SYSTEM_PYTHON = "/usr/bin/python3"
CHECK_SCRIPT = Path(__file__).with_name("_cloud_init_check.py")
INSTALL_HINT = "run scripts/install-host-tools as root"


class SeedToolError(RuntimeError):
    """cloud-init's or netplan's check cannot run here: no seed is written."""


def cache_dir() -> Path:
    return Path(os.environ.get("ROSLAB_CACHE_DIR", "/var/cache/roslab")) / "seed-tools"


def _run(argv, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, check=False, **kwargs)


def _candidate_versions() -> str:
    """The versions apt would download, as one key (a new version unpacks anew)."""
    versions = []
    for package in PACKAGES:
        result = _run(["apt-cache", "policy", package])
        candidate = next((line.split(":", 1)[1].strip() for line in result.stdout.splitlines()
                          if line.strip().startswith("Candidate:")), "")
        if result.returncode != 0 or not candidate or candidate == "(none)":
            raise SeedToolError(f"apt has no {package} package to check seeds with "
                                f"(`apt-cache policy {package}`); is Debian's archive configured?")
        versions.append(f"{package}_{candidate}".replace(":", "%"))
    return "-".join(versions)


def unpacked_root() -> Path:
    """The directory Debian's cloud-init and netplan are unpacked into (fetched once)."""
    base = cache_dir()
    # A cached root that exists is used as it is: no apt query on every run.
    existing = sorted(base.glob("*/.complete")) if base.is_dir() else []
    if existing:
        return existing[-1].parent
    version = _candidate_versions()
    root = base / version
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise SeedToolError(f"cannot create {base} ({error.strerror}): set ROSLAB_CACHE_DIR to a "
                            f"directory you can write, or {INSTALL_HINT}") from None
    import fcntl

    with open(base / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (root / ".complete").exists():
            return root
        staging = Path(tempfile.mkdtemp(dir=base, prefix=".unpack-"))
        try:
            result = _run(["apt-get", "download", *PACKAGES], cwd=staging)
            debs = sorted(staging.glob("*.deb"))
            if result.returncode != 0 or len(debs) != len(PACKAGES):
                raise SeedToolError(f"`apt-get download {' '.join(PACKAGES)}` failed: "
                                    f"{(result.stderr or result.stdout).strip()[-300:]}")
            for deb in debs:
                unpacked = _run(["dpkg-deb", "-x", str(deb), str(staging / "root")])
                if unpacked.returncode != 0:
                    raise SeedToolError(f"dpkg-deb -x {deb.name} failed: {unpacked.stderr.strip()}")
                deb.unlink()
            (staging / "root" / ".complete").write_text(version + "\n")
            if root.exists():
                shutil.rmtree(root)
            os.rename(staging / "root", root)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return root


def _python_path(root: Path) -> Path:
    return root / "usr/lib/python3/dist-packages"


def check_user_data(documents: dict[str, str], secrets: list[str]) -> dict[str, list[str]]:
    """cloud-init's problems with each user-data (name -> problems; empty lists when valid)."""
    root = unpacked_root()
    if not Path(SYSTEM_PYTHON).exists():
        raise SeedToolError(f"{SYSTEM_PYTHON} is missing; cloud-init's check needs Debian's python3")
    environment = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LANG": "C.UTF-8",
                   "PYTHONPATH": str(_python_path(root))}
    result = _run([SYSTEM_PYTHON, "-s", str(CHECK_SCRIPT)],
                  input=json.dumps(documents), env=environment)
    if result.returncode != 0:
        last = _mask(result.stderr.strip().splitlines()[-1] if result.stderr.strip() else "no output", secrets)
        raise SeedToolError(f"cloud-init's schema check could not run ({last}); {INSTALL_HINT}")
    problems = json.loads(result.stdout)
    return {name: [_mask(problem, secrets) for problem in found] for name, found in problems.items()}


def check_network_config(name: str, text: str, secrets: list[str]) -> list[str]:
    """netplan's problems with one network-config (as cloud-init would hand it to netplan)."""
    root = unpacked_root()
    generate = next((path for path in (root / "usr/libexec/netplan/generate", root / "lib/netplan/generate")
                     if path.is_file()), None)
    if generate is None:
        raise SeedToolError(f"netplan's generator is missing from {root}; delete that directory "
                            "and run roslab seed again")
    with tempfile.TemporaryDirectory(prefix="roslab-netplan-") as scratch:
        netplan_dir = Path(scratch) / "etc/netplan"
        netplan_dir.mkdir(parents=True)
        staged = netplan_dir / "50-cloud-init.yaml"
        fd = os.open(staged, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(text)
        result = _run([str(generate), "--root-dir", scratch],
                      env={"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LANG": "C.UTF-8",
                           "LD_LIBRARY_PATH": str(root / "usr/lib/x86_64-linux-gnu") + ":"
                           + str(root / "usr/lib/aarch64-linux-gnu")})
    if result.returncode == 0:
        return []
    output = (result.stderr or result.stdout).strip().replace(str(staged), name)
    if "error while loading shared libraries" in output:
        raise SeedToolError(f"netplan's generator cannot run here: {output.splitlines()[0]}")
    return [_mask(line, secrets) for line in output.splitlines() if line.strip()][:3]


def _mask(text: str, secrets: list[str]) -> str:
    text = mask_secrets(text)
    for secret in sorted(secrets, key=len, reverse=True):
        if secret:
            text = text.replace(secret, "********")
    return text
