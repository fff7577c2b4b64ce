"""The ROS 2 packages in nodes/: metadata, entry points, launch files and parameters.

These check, without ROS, what `colcon build`, `rosdep install`, `ros2 run` and
`ros2 launch` rely on. Checks that need a ROS runtime skip with the reason.
"""

import ast
import configparser
import importlib.util
import sys
from glob import glob
from pathlib import Path

import pytest
import yaml
from catkin_pkg.package import parse_package

NODES_DIR = Path(__file__).resolve().parents[2] / "nodes"
DEMO_DIR = NODES_DIR / "roslab_demo"
BRINGUP_DIR = NODES_DIR / "roslab_bringup"
LAUNCH_FILES = sorted((BRINGUP_DIR / "launch").glob("*.launch.py"))

sys.path.insert(0, str(DEMO_DIR))

from roslab_demo.logic import PARAMETERS  # noqa: E402  (importable only once the path is set)

# Which node runs where: the robot publishes, its team's main host listens.
ROLE_NODES = {
    "robot": {"talker", "status_publisher", "temperature_publisher"},
    "main": {"listener", "status_monitor", "temperature_monitor"},
}

# Python import names that are not ROS packages of the same name.
IMPORT_TO_ROSDEP_KEY = {"pytest": "python3-pytest", "catkin_pkg": "python3-catkin-pkg"}


def package_dirs():
    return sorted(path.parent for path in NODES_DIR.glob("*/package.xml"))


def setup_arguments(package_dir, monkeypatch):
    """Return the keyword arguments setup.py passes to setup(), without running setuptools."""
    tree = ast.parse((package_dir / "setup.py").read_text())
    namespace = {"glob": glob}
    for statement in tree.body:
        if isinstance(statement, ast.Assign) and isinstance(statement.value, ast.Constant):
            namespace[statement.targets[0].id] = statement.value.value
    (call,) = [
        node.value
        for node in tree.body
        if isinstance(node, ast.Expr) and getattr(node.value.func, "id", None) == "setup"
    ]
    monkeypatch.chdir(package_dir)  # setup.py's globs are relative to the package, as in colcon
    return {
        keyword.arg: eval(compile(ast.Expression(keyword.value), "setup.py", "eval"), namespace)
        for keyword in call.keywords
    }


def console_scripts(package_dir, monkeypatch):
    """Return {executable: (module, function)} from setup.py's console_scripts."""
    entries = setup_arguments(package_dir, monkeypatch).get("entry_points", {})
    scripts = {}
    for entry in entries.get("console_scripts", []):
        name, target = (part.strip() for part in entry.split("="))
        module, function = target.split(":")
        scripts[name] = (module, function)
    return scripts


def python_sources(package_dir):
    """The package's own Python files: modules and launch files, not setup.py or tests."""
    return [
        path
        for path in package_dir.rglob("*.py")
        if path.name != "setup.py" and "test" not in path.relative_to(package_dir).parts
    ]


def imported_top_level_names(paths):
    names = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names)


def launched_nodes(launch_file):
    """Return (package, executable, name) for every Node(...) in a launch file."""
    found = []
    for node in ast.walk(ast.parse(launch_file.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Node":
            arguments = {kw.arg: kw.value for kw in node.keywords}
            fields = ("package", "executable", "name")
            found.append(tuple(ast.literal_eval(arguments[key]) for key in fields))
    return found


def node_modules():
    """roslab_demo's node modules: those with a main() for a console script."""
    return sorted(
        path
        for path in (DEMO_DIR / "roslab_demo").glob("*.py")
        if any(
            isinstance(node, ast.FunctionDef) and node.name == "main"
            for node in ast.parse(path.read_text()).body
        )
    )


# --- package.xml -------------------------------------------------------------------


def test_nodes_holds_the_packages_the_workspace_deploy_launches():
    assert [path.name for path in package_dirs()] == ["roslab_bringup", "roslab_demo", "roslab_esp32"]


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_package_xml_is_valid_format_3_for_ament_python(package_dir):
    warnings = []
    package = parse_package(str(package_dir), warnings=warnings)  # validates, as rosdep does
    assert warnings == []
    assert package.package_format == 3
    assert package.name == package_dir.name
    assert package.get_build_type() == "ament_python"
    assert package.licenses == ["Apache-2.0"]


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_every_ros_package_the_code_imports_or_launches_is_an_exec_depend(package_dir):
    # Otherwise `rosdep install` would not install it and the node fails at start-up.
    package = parse_package(str(package_dir))
    exec_depends = {dep.name for dep in package.exec_depends}
    needed = imported_top_level_names(python_sources(package_dir)) - {package.name}
    for launch_file in package_dir.glob("launch/*.launch.py"):
        needed |= {pkg for pkg, _, _ in launched_nodes(launch_file)}
    assert needed, "found no imports: the scan is broken"
    assert needed <= exec_depends, f"missing exec_depend: {sorted(needed - exec_depends)}"


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_the_linters_the_package_tests_import_are_test_depends(package_dir):
    package = parse_package(str(package_dir))
    test_depends = {dep.name for dep in package.test_depends}
    imported = imported_top_level_names((package_dir / "test").glob("test_*.py"))
    needed = {IMPORT_TO_ROSDEP_KEY.get(name, name) for name in imported}
    assert needed == {
        "ament_copyright",
        "ament_flake8",
        "ament_pep257",
        "python3-catkin-pkg",
        "python3-pytest",
    }
    assert needed <= test_depends
    # The offline XML lint runs the xmllint that ament_xmllint's package brings (libxml2-utils).
    assert "ament_xmllint" in test_depends


def test_bringup_runs_the_roslab_bringup_launch_with_ros2_launch():
    # The systemd unit runs `ros2 launch`, which comes from the ros2launch package.
    exec_depends = {dep.name for dep in parse_package(str(BRINGUP_DIR)).exec_depends}
    assert "ros2launch" in exec_depends


# --- setup.py / setup.cfg ------------------------------------------------------------


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_setup_py_names_the_package_and_installs_its_marker_and_manifest(
    package_dir, monkeypatch
):
    arguments = setup_arguments(package_dir, monkeypatch)
    name = package_dir.name
    assert arguments["name"] == name
    assert arguments["version"] == parse_package(str(package_dir)).version
    data_files = dict(arguments["data_files"])
    # The ament index marker is how `ros2 run` and `ros2 launch` find the package at all.
    assert data_files["share/ament_index/resource_index/packages"] == [f"resource/{name}"]
    assert (package_dir / "resource" / name).is_file()
    assert "package.xml" in data_files[f"share/{name}"]


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_setup_py_installs_every_launch_and_config_file(package_dir, monkeypatch):
    data_files = dict(setup_arguments(package_dir, monkeypatch)["data_files"])
    for folder in ("launch", "config"):
        on_disk = sorted(
            str(path.relative_to(package_dir)) for path in (package_dir / folder).glob("*")
        )
        installed = sorted(data_files.get(f"share/{package_dir.name}/{folder}", []))
        assert installed == on_disk


def test_bringup_ships_a_launch_file_per_role_and_the_parameters(monkeypatch):
    data_files = dict(setup_arguments(BRINGUP_DIR, monkeypatch)["data_files"])
    assert sorted(data_files["share/roslab_bringup/launch"]) == [
        "launch/esp32.launch.py",
        "launch/main.launch.py",
        "launch/robot.launch.py",
    ]
    assert data_files["share/roslab_bringup/config"] == ["config/params.yaml"]


@pytest.mark.parametrize("package_dir", package_dirs(), ids=lambda p: p.name)
def test_setup_cfg_installs_scripts_where_ros2_run_looks(package_dir):
    config = configparser.ConfigParser()
    assert config.read(package_dir / "setup.cfg")
    expected = f"$base/lib/{package_dir.name}"
    assert config["develop"]["script_dir"] == expected
    assert config["install"]["install_scripts"] == expected


def test_each_console_script_points_at_an_existing_function(monkeypatch):
    scripts = console_scripts(DEMO_DIR, monkeypatch)
    assert scripts
    for executable, (module, function) in scripts.items():
        path = DEMO_DIR / (module.replace(".", "/") + ".py")
        assert path.is_file(), f"{executable}: no module {module}"
        tree = ast.parse(path.read_text())
        functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
        assert function in functions, f"{executable}: {module} has no {function}()"


def test_every_node_module_has_a_console_script(monkeypatch):
    targets = {module for module, _ in console_scripts(DEMO_DIR, monkeypatch).values()}
    modules = {f"roslab_demo.{path.stem}" for path in node_modules()}
    assert len(modules) == 6
    assert modules == targets


# --- nodes -----------------------------------------------------------------------


def node_class_facts(path):
    """Return (name passed to Node.__init__, table key passed to declare_parameters)."""
    node_name = table_key = None
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Call) or not node.args:
            continue
        func = node.func
        if isinstance(func, ast.Attribute) and func.attr == "__init__":
            node_name = ast.literal_eval(node.args[0])
        elif getattr(func, "id", None) == "declare_parameters":
            table_key = ast.literal_eval(node.args[1])
    return node_name, table_key


@pytest.mark.parametrize("path", node_modules(), ids=lambda p: p.stem)
def test_node_declares_the_parameters_listed_under_its_own_name(path):
    # params.yaml sections are keyed by node name: a mismatch silently drops the file's values.
    node_name, table_key = node_class_facts(path)
    assert node_name == table_key == path.stem
    assert node_name in PARAMETERS


@pytest.mark.parametrize("path", node_modules(), ids=lambda p: p.stem)
def test_node_main_shuts_down_cleanly_on_ctrl_c_and_launch_shutdown(path):
    # Without this, Ctrl-C or stopping the systemd unit prints a traceback and
    # "rcl_shutdown already called" errors.
    (main,) = [
        node
        for node in ast.parse(path.read_text()).body
        if isinstance(node, ast.FunctionDef) and node.name == "main"
    ]
    (try_block,) = [node for node in ast.walk(main) if isinstance(node, ast.Try)]
    caught = {
        ast.unparse(element)
        for handler in try_block.handlers
        for element in getattr(handler.type, "elts", [handler.type])
    }
    assert caught == {"KeyboardInterrupt", "ExternalShutdownException"}
    final_calls = {
        ast.unparse(node.func)
        for statement in try_block.finalbody
        for node in ast.walk(statement)
        if isinstance(node, ast.Call)
    }
    assert {"node.destroy_node", "rclpy.try_shutdown"} <= final_calls
    # Ctrl-C signals every process of a launch and ros2 launch forwards another SIGINT: the
    # clean-up first ignores it, or the second one ends it in a KeyboardInterrupt traceback.
    first = ast.unparse(try_block.finalbody[0])
    assert first == "signal.signal(signal.SIGINT, signal.SIG_IGN)", first
    calls = [ast.unparse(node.func) for node in ast.walk(main) if isinstance(node, ast.Call)]
    assert "rclpy.init" in calls
    assert calls.index("end_on_first_interrupt") < calls.index("rclpy.init")


# --- launch files and parameters ---------------------------------------------------


@pytest.mark.parametrize("launch_file", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_defines_generate_launch_description(launch_file):
    tree = ast.parse(launch_file.read_text())
    assert "generate_launch_description" in {
        node.name for node in tree.body if isinstance(node, ast.FunctionDef)
    }


@pytest.mark.parametrize("role", sorted(ROLE_NODES))
def test_each_role_launches_its_nodes_under_their_own_names(role, monkeypatch):
    nodes = launched_nodes(BRINGUP_DIR / "launch" / f"{role}.launch.py")
    executables = console_scripts(DEMO_DIR, monkeypatch)
    assert {name for _, _, name in nodes} == ROLE_NODES[role]
    for package, executable, name in nodes:
        assert package == "roslab_demo"
        assert executable in executables, f"{role}.launch.py runs unknown {executable}"
        assert name == executable  # the name params.yaml and PARAMETERS are keyed by


@pytest.mark.parametrize("launch_file", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_builds_a_launch_description(launch_file):
    pytest.importorskip("launch", reason="ROS 2 'launch' is not installed (no ROS runtime here)")
    pytest.importorskip("launch_ros", reason="ROS 2 'launch_ros' is not installed here")
    from launch import LaunchDescription

    spec = importlib.util.spec_from_file_location(launch_file.stem.replace(".", "_"), launch_file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert isinstance(module.generate_launch_description(), LaunchDescription)


def test_params_yaml_repeats_every_parameter_default_with_its_type():
    # ROS parameters are typed: a float parameter refuses `publish_rate_hz: 1` (an int).
    params = yaml.safe_load((BRINGUP_DIR / "config" / "params.yaml").read_text())
    from_yaml = {
        node: {key: (type(value), value) for key, value in section["ros__parameters"].items()}
        for node, section in params.items()
    }
    from_table = {
        node: {key: (type(spec.default), spec.default) for key, spec in table.items()}
        for node, table in PARAMETERS.items()
    }
    assert from_yaml == from_table


def test_every_launched_node_has_a_parameter_section():
    params = yaml.safe_load((BRINGUP_DIR / "config" / "params.yaml").read_text())
    # esp32.launch.py runs roslab_esp32's node, which has no parameters of roslab_demo's.
    launched = {name for path in LAUNCH_FILES if path.name != "esp32.launch.py"
                for _, _, name in launched_nodes(path)}
    assert launched == set(params) == set(PARAMETERS)


# --- with a ROS runtime ------------------------------------------------------------


@pytest.mark.parametrize("path", node_modules(), ids=lambda p: p.stem)
def test_node_starts_with_the_default_parameters(path):
    rclpy = pytest.importorskip(
        "rclpy", reason="rclpy is not installed: no ROS 2 runtime on this machine"
    )
    from rclpy.node import Node

    module = importlib.import_module(f"roslab_demo.{path.stem}")
    (node_class,) = [
        value
        for value in vars(module).values()
        if isinstance(value, type)
        and issubclass(value, Node)
        and value.__module__ == module.__name__
    ]
    rclpy.init()
    try:
        node = node_class()
        try:
            actual = {name: node.get_parameter(name).value for name in PARAMETERS[path.stem]}
            assert actual == {name: spec.default for name, spec in PARAMETERS[path.stem].items()}
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("launch_file", LAUNCH_FILES, ids=lambda p: p.name)
def test_every_launched_node_ends_the_launch_when_it_ends(launch_file):
    # The nodes service follows the life of every node it runs: a node that crashes or is
    # killed ends the launch (on_exit=Shutdown), and systemd starts them all again.
    tree = ast.parse(launch_file.read_text())
    nodes = [node for node in ast.walk(tree)
             if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Node"]
    assert nodes
    for node in nodes:
        on_exit = {kw.arg: kw.value for kw in node.keywords}.get("on_exit")
        assert on_exit is not None and ast.unparse(on_exit).startswith("Shutdown("), ast.unparse(node)
