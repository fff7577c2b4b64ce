"""Facts and the operation for a robot profile's Python venv (deploy/python_env.py).

    PythonTarget                  the host's machine, glibc and python3 (what the wheelhouse is for)
    VenvState                     a venv's Python, its COLCON_IGNORE and its requirements stamp
    venv_requirements_installed   the venv exists and holds exactly the wheelhouse's requirements
    venv_on_pythonpath            shell: the venv's site-packages first on PYTHONPATH
"""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import FactBase, operation

from roslab.quoting import shell_word

STAMP = ".roslab-requirements"  # in the venv: the digest of the requirement set installed last


def venv_on_pythonpath(venv_word: str) -> str:
    """Shell that puts a venv's site-packages first on PYTHONPATH, if the venv is there.

    `venv_word`: the venv's directory as one shell word (`shell_word`, `shell_home_path`).
    ROS runs Python nodes with the interpreter of their shebang (/usr/bin/python3), never the
    venv's, so activating the venv would not reach them: PYTHONPATH does, for `ros2 run`,
    `ros2 launch` and plain `python3` alike. A glob (the venv's one python3.X), not a Python
    call: a shell on a Pi 3 starts no interpreter for it.
    """
    # once: a nested shell sources ~/.bashrc again; one { group }, so a unit can chain it with &&
    return (f"{{ for roslab_site in {venv_word}/lib/python3*/site-packages; do "
            'case ":${PYTHONPATH:-}:" in *":$roslab_site:"*) ;; *) if [ -d "$roslab_site" ]; then '
            'export PYTHONPATH="$roslab_site${PYTHONPATH:+:$PYTHONPATH}"; fi ;; esac; '
            "done; unset roslab_site; }")


class PythonTarget(FactBase):
    """{"machine", "glibc", "python"} of the host (`uname -m`, glibc's version, python3's
    major.minor); "none" for what is missing."""

    def command(self) -> str:
        return ("echo \"machine $(uname -m)\"; "
                "echo \"glibc $(getconf GNU_LIBC_VERSION 2>/dev/null | sed -n 's/^glibc //p')\"; "
                "echo \"python $(python3 -c 'import sys; print(\"%d.%d\" % sys.version_info[:2])' "
                "2>/dev/null)\"")

    def process(self, output):
        found = {"machine": "none", "glibc": "none", "python": "none"}
        for line in output:
            key, _, value = line.strip().partition(" ")
            if key in found and value.strip():
                found[key] = value.strip()
        return found


class VenvState(FactBase):
    """{"python": the venv's Python major.minor or None, "colcon_ignore": bool, "stamp": str}."""

    def command(self, path: str) -> str:
        word = shell_word(path)
        return (f"p={word}; "
                "if [ -x \"$p/bin/python\" ] && [ -f \"$p/pyvenv.cfg\" ]; then "
                "echo \"python $(sed -n 's/^version[_info]* *= *\\([0-9]*\\.[0-9]*\\).*/\\1/p' "
                "\"$p/pyvenv.cfg\" | head -n 1)\"; fi; "
                "if [ -e \"$p/COLCON_IGNORE\" ]; then echo colcon_ignore; fi; "
                f"echo \"stamp $(head -c 64 \"$p/{STAMP}\" 2>/dev/null)\"")

    def process(self, output):
        state = {"python": None, "colcon_ignore": False, "stamp": ""}
        for line in output:
            key, _, value = line.strip().partition(" ")
            if key == "python" and value.strip():
                state["python"] = value.strip()
            elif key == "colcon_ignore":
                state["colcon_ignore"] = True
            elif key == "stamp":
                state["stamp"] = value.strip()
        return state


def pip_install_command(venv: str, wheelhouse: str, requirements_file: str, stamp: str) -> str:
    """pip installs the requirements from the pushed files alone; a failure is one `roslab:` line
    naming the venv and pip's first error (which names the package), and leaves the stamp alone."""
    venv_word, stamp_word = shell_word(venv), shell_word(f"{venv}/{STAMP}")
    return (
        "log=$(mktemp) && "
        f"if {shell_word(venv + '/bin/python')} -m pip install --no-index --find-links {shell_word(wheelhouse)} "
        f"-r {shell_word(requirements_file)} --disable-pip-version-check --no-input --progress-bar off "
        '>"$log" 2>&1; then '
        f"rm -f \"$log\"; printf '%s\\n' {shell_word(stamp)} > {stamp_word}; "
        "else cat \"$log\" >&2; "
        "reason=$(grep -m 1 '^ERROR:' \"$log\" || tail -n 1 \"$log\"); rm -f \"$log\"; "
        f"echo \"roslab: pip could not install the requirements into \"{venv_word}\": $reason\" >&2; "
        "exit 1; fi"
    )


@operation()
def venv_requirements_installed(venv: str, python: str, wheelhouse: str | None = None,
                                requirements_file: str | None = None, stamp: str = ""):
    """A venv with the system's site packages (COLCON_IGNORE in it) holding the requirements.

    + venv: the venv's absolute path (run the operation as its owner: ``_sudo_user``)
    + python: the host's python3 major.minor; a venv made by another Python is made again
    + wheelhouse: the host folder pip installs from (``--no-index --find-links``); None: no requirements
    + requirements_file: the pinned requirements in that folder
    + stamp: the requirement set's digest; pip runs only when the venv's stamp differs

    Example: ``venv_requirements_installed(name="...", venv="/home/ubuntu/osr_venv", python="3.12",
    wheelhouse="/var/cache/roslab/wheelhouse", requirements_file=".../requirements.txt", stamp=digest)``
    """
    state = host.get_fact(VenvState, path=venv)
    word = shell_word(venv)
    made = False
    if state["python"] != python:
        if state["python"] is not None:  # a venv of the Python before a release upgrade
            yield f"rm -rf -- {word}"
        yield f"python3 -m venv --system-site-packages {word}"
        made = True
    if made or not state["colcon_ignore"]:
        # colcon does not crawl into the venv when it lies inside a workspace.
        yield f"touch {shell_word(venv + '/COLCON_IGNORE')}"
    if wheelhouse and requirements_file and (made or state["stamp"] != stamp):
        yield pip_install_command(venv, wheelhouse, requirements_file, stamp)
    elif not made and state["colcon_ignore"]:
        host.noop(f"{venv} (Python {python}) already holds this requirement set"
                  if wheelhouse else f"{venv} (Python {python}) already exists")


def venv_requirements_installed_reads(venv: str) -> list:
    from roslab import probe

    return [probe.read(VenvState, path=venv)]


def python_target_reads() -> list:
    from roslab import probe

    return [probe.read(PythonTarget)]
