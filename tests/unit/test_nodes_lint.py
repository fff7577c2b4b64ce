"""nodes/ passes flake8 as `colcon test` runs it on a ROS host (ament_flake8), without ROS.

Each package's test/test_flake8.py calls ament_flake8, which runs flake8 with the
configuration file ament_flake8 ships and whatever flake8 plugins the host has. Here
the same flake8 runs with a copy of that configuration and the plugins of the `test`
extra (pyproject.toml), so an import in the wrong order fails roslab's own suite
instead of first showing up on a Pi.
"""

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

NODES_DIR = Path(__file__).resolve().parents[2] / "nodes"

# Mirrors ament_flake8/configuration/ament_flake8.ini as shipped with ROS 2 Humble
# (ament_flake8 0.12) and Jazzy (0.17): the two are the same. ament_flake8 sets no
# application-import-names, so with the google style our own packages' imports
# (`from roslab_demo.logic import ...`) count as third-party and sort alphabetically
# among rclpy, sensor_msgs and std_msgs, in one group. I202 (a blank line inside a
# group) is ignored, so such a blank line does not make a separate group.
AMENT_FLAKE8_INI = """\
[flake8]
extend-ignore = B902,C816,D100,D101,D102,D103,D104,D105,D106,D107,D203,D212,D404,I202
import-order-style = google
max-line-length = 99
show-source = true
statistics = true
"""

# The flake8 plugins a ROS 2 developer host has, each with a code only it reports.
# Jazzy's ament_flake8 depends on flake8-docstrings and flake8-import-order; ROS 2's
# development setup installs the others too. Passing with all of them passes with any
# subset. A plugin that is not installed reports nothing, so each needs this proof.
PLUGIN_PROBES = {
    "flake8-import-order": ("import sys\nimport os\n\nprint(os, sys)\n", "I100"),
    "flake8-docstrings": ('def f():\n    """Do it"""\n', "D400"),
    "flake8-quotes": ('NAME = "double"\n', "Q000"),
    "flake8-builtins": ("list = [1]\n", "A001"),
    "flake8-comprehensions": ("SQUARES = list([n * n for n in range(3)])\n", "C411"),
    "flake8-blind-except": ("try:\n    pass\nexcept:\n    pass\n", "B901"),
    "flake8-class-newline": ("class C:\n    def f(self):\n        pass\n", "CNL100"),
    "flake8-deprecated": ("import unittest\n\nunittest.TestCase().assertEquals(1, 1)\n", "D001"),
}

FINDING = re.compile(r"^(?P<path>.+?):(?P<row>\d+):(?P<col>\d+): (?P<code>[A-Z]+[0-9]+) ")

# Files the check must reject (or accept), each to prove the check can fail.
WRONG_ORDER = textwrap.dedent('''\
    """A node module whose imports ament_flake8 rejects."""

    import socket
    import rclpy
    from std_msgs.msg import String

    from roslab_demo.logic import chatter_text

    print(socket, rclpy, String, chatter_text)
    ''')
AMENT_ORDER = textwrap.dedent('''\
    """A node module whose imports ament_flake8 accepts."""

    import socket

    import rclpy
    from roslab_demo.logic import chatter_text
    from std_msgs.msg import String

    print(socket, rclpy, String, chatter_text)
    ''')


def line_of(length):
    return "X = '" + "x" * (length - 6) + "'\n"


def ament_flake8(config_dir, *paths):
    """Run flake8 with ament_flake8's configuration; return {path: [finding lines]}, output."""
    config = config_dir / "ament_flake8.ini"
    config.write_text(AMENT_FLAKE8_INI)
    # --config makes this file the only configuration flake8 reads, as ament_flake8 does.
    result = subprocess.run(
        [sys.executable, "-m", "flake8", f"--config={config}", *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    output = result.stdout + result.stderr
    if "No module named flake8" in result.stderr:
        pytest.fail("flake8 is not installed: pip install -e '.[test]'")
    findings = {}
    for line in result.stdout.splitlines():
        match = FINDING.match(line)
        if match:
            findings.setdefault(Path(match["path"]), []).append(line)
    # flake8 exits 1 for findings; anything else (a crash, a bad option) is no lint result.
    assert result.returncode in (0, 1), output
    assert (result.returncode == 1) == bool(findings), output
    return findings, output


def codes(findings):
    return sorted(FINDING.match(line)["code"] for line in findings)


def test_nodes_pass_ament_flake8(tmp_path):
    findings, output = ament_flake8(tmp_path, NODES_DIR)
    assert findings == {}, f"ament_flake8 would fail `colcon test`:\n{output}"


@pytest.fixture(scope="module")
def probes(tmp_path_factory):
    """Lint every probe file in one flake8 run (each run costs most of a second)."""
    base = tmp_path_factory.mktemp("probes")
    files = {
        "wrong_order.py": WRONG_ORDER,
        "ament_order.py": AMENT_ORDER,
        "line_99.py": line_of(99),
        "line_100.py": line_of(100),
    }
    for plugin, (snippet, _) in PLUGIN_PROBES.items():
        files[f"{plugin.replace('-', '_')}.py"] = '"""Probe."""\n\n' + snippet
    sources = base / "src"
    sources.mkdir()
    for name, text in files.items():
        (sources / name).write_text(text)
    findings, output = ament_flake8(base, sources)
    return lambda name: (findings.get(sources / name, []), output)


def test_the_check_reports_imports_in_the_wrong_order(probes):
    # The mistake `colcon test` caught: our package kept apart from, and after,
    # std_msgs; and here also no blank line between the standard library and the rest.
    findings, output = probes("wrong_order.py")
    assert codes(findings) == ["I100", "I201"], output
    assert any(":7:1: I100 " in line and "roslab_demo.logic" in line for line in findings)
    assert any(":4:1: I201 " in line for line in findings)


def test_the_check_accepts_the_same_imports_in_ament_order(probes):
    findings, output = probes("ament_order.py")
    assert findings == [], output


def test_the_check_allows_99_characters_a_line_not_100(probes):
    assert len(line_of(100).rstrip("\n")) == 100
    assert codes(probes("line_99.py")[0]) == []
    assert codes(probes("line_100.py")[0]) == ["E501"]


@pytest.mark.parametrize("plugin", sorted(PLUGIN_PROBES))
def test_each_plugin_of_a_ros_host_is_active(plugin, probes):
    _, code = PLUGIN_PROBES[plugin]
    findings, output = probes(f"{plugin.replace('-', '_')}.py")
    assert code in codes(findings), (
        f"{plugin} reported no {code}: is it installed? pip install -e '.[test]'\n{output}"
    )
