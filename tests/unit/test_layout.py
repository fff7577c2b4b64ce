"""roslab's layout: no import cycle between its folders nor between its files, in roslab/ and deploy/
(lazy imports inside functions count),
no function over 60 lines in roslab/, deploy/ or deploy.py (as bench/code_shape.py counts them),
and robot commands come from the profiles that name them."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest

import roslab
from roslab.profiles.library import builtin_profiles
from roslab.profiles.schema import known_tools

ROOT = Path(roslab.__file__).parent
CHECKOUT = Path(__file__).resolve().parents[2]

# Functions over 60 lines allowed for now, with their length: none may grow, none may join
# them, and one split below 60 leaves this list. Empty since the three roslab/ ones were split.
KNOWN_LONG: dict[str, int] = {}


def _unit(module: str) -> str:
    """roslab.<folder> for a folder's modules, roslab.<module> for a loose one."""
    return ".".join(module.split(".")[:2])


def import_edges() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {}
    for path in ROOT.rglob("*.py"):
        module = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts).removesuffix(".__init__")
        source = _unit(module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("roslab"):
                targets = [f"roslab.{alias.name}" for alias in node.names] if node.module == "roslab" \
                    else [node.module]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names if alias.name.startswith("roslab.")]
            else:
                continue
            for target in targets:
                if _unit(target) != source:
                    edges.setdefault(source, set()).add(_unit(target))
    return edges


def module_name(path: Path, root: Path) -> str:
    """The dotted name of the module at `path` (a package's __init__.py: the package)."""
    return ".".join(path.relative_to(root.parent).with_suffix("").parts).removesuffix(".__init__")


def file_import_edges(root: Path | None = None) -> dict[str, set[str]]:
    """Module -> the modules of the same tree it imports, each file a node (lazy imports inside
    functions count). Relative imports are resolved; `from pkg import name` is an edge to
    pkg.name when that is a module, else to pkg (its __init__.py)."""
    root = root or ROOT
    paths = {module_name(path, root): path for path in root.rglob("*.py")}
    top = root.name
    edges: dict[str, set[str]] = {}
    for module, path in paths.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    source = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    source = node.module or ""
                if source != top and not source.startswith(top + "."):
                    continue
                targets = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in paths else source
                           for alias in node.names]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names if alias.name.startswith(top + ".")]
            else:
                continue
            for target in targets:
                while target not in paths and "." in target:  # `import a.b.c` of a name, not a file
                    target = target.rpartition(".")[0]
                if target in paths and target != module:
                    edges.setdefault(module, set()).add(target)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one unit (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for successor in edges.get(node, ()):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in list(edges):
        if node not in index:
            visit(node)
    return found


def test_no_import_cycle_runs_through_a_folder():
    folders = {f"roslab.{path.parent.name}" for path in ROOT.glob("*/__init__.py")}
    through_folders = [component for component in cycles(import_edges()) if folders & set(component)]
    assert through_folders == []


def test_no_import_cycle_at_all_not_even_between_two_loose_modules():
    # a folder counts as one unit here (issue 42's facts <-> operations was the last cycle)
    assert cycles(import_edges()) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_between_files_in_roslab_or_deploy():
    # each module a node (a folder's modules too, and roslab.ops' tools among them)
    assert cycles(file_import_edges(ROOT)) == []
    assert cycles(file_import_edges(CHECKOUT / "deploy")) == []


def test_the_file_level_cycle_finder_resolves_imports_and_finds_a_planted_cycle(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("X = 1\n")
    (package / "sub/__init__.py").write_text("")
    (package / "a.py").write_text("from . import b\n")  # relative: pkg.b, a module
    (package / "b.py").write_text("from .sub.c import thing\n")
    (package / "sub/c.py").write_text("def thing():\n    from pkg import a  # lazy, still an edge\n")
    (package / "d.py").write_text("from pkg import X\nimport pkg.sub.c\nimport os\n")
    (package / "sub/e.py").write_text("from .. import d\nfrom ..sub import c\n")
    edges = file_import_edges(package)
    assert edges["pkg.d"] == {"pkg", "pkg.sub.c"}  # X is a name in pkg/__init__.py, not a module
    assert edges["pkg.sub.e"] == {"pkg.d", "pkg.sub.c"}
    assert cycles(edges) == [["pkg.a", "pkg.b", "pkg.sub.c"]]


def code_shape():
    """bench/code_shape.py, the measure the reviews quote."""
    spec = importlib.util.spec_from_file_location("code_shape", CHECKOUT / "bench/code_shape.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def long_functions(root: Path) -> dict[str, int]:
    """{"<path> <function>": length} of the functions over 60 lines that code_shape finds under `root`."""
    return {f"{where.split(':')[0]} {where.split(' ', 1)[1]}": length
            for length, where in code_shape().shape(root)["long"]}


def test_no_function_in_roslab_deploy_or_deploy_py_is_over_60_lines():
    measured = {name.split("/")[0] for name in code_shape().shape(CHECKOUT)["modules"]}
    assert measured == {"roslab", "deploy", "deploy.py"}
    found = long_functions(CHECKOUT)
    new_or_grown = {name: length for name, length in found.items() if length > KNOWN_LONG.get(name, 60)}
    assert new_or_grown == {}, "split these into named steps or helpers (under 60 lines each)"
    split = sorted(set(KNOWN_LONG) - set(found))
    assert split == [], "under 60 lines now: take them out of KNOWN_LONG"


def test_the_length_rule_sees_a_long_function_in_each_tree(tmp_path):
    def function(name: str, lines: int) -> str:
        return f"def {name}():\n" + "    x = 1\n" * (lines - 1)

    (tmp_path / "roslab").mkdir()
    (tmp_path / "deploy").mkdir()
    (tmp_path / "roslab/a.py").write_text(function("long_one", 61) + function("short_one", 60))
    (tmp_path / "deploy/b.py").write_text("class C:\n    " + function("method", 61).replace("\n", "\n    "))
    (tmp_path / "deploy.py").write_text("if True:\n    " + function("nested", 62).replace("\n", "\n    "))
    assert long_functions(tmp_path) == {"roslab/a.py long_one": 61, "deploy/b.py method": 61,
                                        "deploy.py nested": 62}


def test_robot_commands_are_the_ones_profiles_name():
    from roslab.cli.main import build_parser

    named = {tool for profile in builtin_profiles().values() for tool in profile.tools}
    assert named == {"opencr-update", "esp32-firmware"} and set(known_tools()) >= named
    parser = build_parser()
    commands = next(action for action in parser._actions if action.dest == "command").choices
    assert named <= set(commands)


@pytest.mark.parametrize("tools", ["[flash-everything]", "[opencr_update]", "opencr-update", "['../x']"])
def test_a_profile_naming_a_tool_roslab_lacks_is_refused(tmp_path, tools):
    from roslab.roster import RosterError, load_roster

    path = tmp_path / "lab.yaml"
    path.write_text(f"""\
classroom:
  ssh_user: ubuntu
profiles:
  mine:
    extends: demo
    tools: {tools}
teams:
  t1:
    robot_profile: mine
    hosts:
      t1-robot: {{role: robot}}
""")
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert any("lab.yaml:6: field 'profiles.mine.tools'" in str(problem) for problem in raised.value.problems), \
        raised.value.problems


# Issue 42: a host's settings are read typed, down to every helper. pyinfra's `host.data` is
# the one mapping a deploy may read (the run's own notes, the boundary host_settings builds
# from); nothing reads a mapping out of a host's typed settings.
PYINFRA_HOSTS = {"host", "some_host"}  # the names deploy/ gives pyinfra's Host
TYPED_BUILDERS = {"host_settings", "peer_settings", "settings_of"}


def mapping_reads(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, expression) of each `.data` read off a host's typed settings: `<builder>(...).data`,
    `typed.data`, `<x>.settings.data`."""
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and node.attr == "data"):
            continue
        value = node.value
        built = isinstance(value, ast.Call) and getattr(value.func, "id", getattr(value.func, "attr", None)) \
            in TYPED_BUILDERS
        named = isinstance(value, ast.Name) and value.id in {"typed", "settings"}
        attribute = isinstance(value, ast.Attribute) and value.attr == "settings"
        if built or named or attribute:
            found.append((node.lineno, ast.unparse(node)))
    return found


def deploy_data_reads(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, expression) of each `.data` a deploy reads off anything but pyinfra's Host."""
    return [(node.lineno, ast.unparse(node)) for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and node.attr == "data"
            and not (isinstance(node.value, ast.Name) and node.value.id in PYINFRA_HOSTS)]


def test_no_helper_is_handed_a_mapping_out_of_a_hosts_typed_settings():
    trees = {path: ast.parse(path.read_text()) for path in [
        *ROOT.rglob("*.py"), *(CHECKOUT / "deploy").glob("*.py"), CHECKOUT / "deploy.py"]}
    assert {str(path.relative_to(CHECKOUT)): found for path, tree in trees.items()
            if (found := mapping_reads(tree))} == {}
    deploys = {path: tree for path, tree in trees.items() if path.parent.name == "deploy" or path.name == "deploy.py"}
    assert {str(path.relative_to(CHECKOUT)): found for path, tree in deploys.items()
            if (found := deploy_data_reads(tree))} == {}


def test_the_typed_settings_rule_sees_each_way_back_to_a_mapping():
    source = ("a(typed.data)\nb(host_settings(host).data)\nc(peer_settings(x).data)\n"
              "d(classroom.hosts[0].settings.data)\ne(host.data)\nf(some_host.data.get('k'))\n")
    assert [line for line, _ in mapping_reads(ast.parse(source))] == [1, 2, 3, 4]
    assert [line for line, _ in deploy_data_reads(ast.parse(source))] == [1, 2, 3, 4]
    from roslab.host_fields import HostSettings
    assert "data" not in HostSettings.__dataclass_fields__  # no embedded mapping to hand on


def test_code_shape_reports_file_cycles_and_the_tool_modules(tmp_path, capsys):
    (tmp_path / "roslab/ops").mkdir(parents=True)
    (tmp_path / "roslab/__init__.py").write_text("")
    (tmp_path / "roslab/ops/__init__.py").write_text("")
    (tmp_path / "roslab/a.py").write_text("from roslab import b\n")
    (tmp_path / "roslab/b.py").write_text("def f():\n    import roslab.a\n")
    (tmp_path / "roslab/ops/tool.py").write_text(
        "from pyinfra.api import FactBase, operation\n\nclass Seen(FactBase):\n    pass\n\n"
        "@operation()\ndef done():\n    yield 'true'\n")
    shape = code_shape()
    assert shape.file_cycles(tmp_path) == [["roslab.a", "roslab.b"]]
    shape.main(["code_shape.py", str(tmp_path)])
    printed = capsys.readouterr().out
    assert "- import cycles between files: 1 [['roslab.a', 'roslab.b']]" in printed
    assert "1 of them tool modules in roslab/ops/ (1 facts, 1 operations), 0 elsewhere" in printed
    assert "- roslab/ops/tool.py: 1 facts, 1 operations" in printed


# The same everywhere in roslab/, roster, status, verify and seed too: a host's settings are read
# typed (a roster Host's `.settings`, `host_settings(host)` for pyinfra's Host); a host's mapping
# (`<host>.data`, or any `.data` but a call's) is read only where it is the boundary, or is not a
# host's settings at all, each place named here with why.
MAPPING_BOUNDARY = {
    "roslab/host_settings.py::host_settings": "builds a pyinfra host's typed settings from its data, once per run",
    "roslab/pyinfra_planning.py::host_data_lookup": "the pyinfra patch that reads pyinfra's own data layers once",
    "roslab/network/confirm.py::_connect_at": "a pyinfra connector's connection data, not the host's settings",
    "roslab/network/settings.py::validate_roster": "which network keys the roster itself gave (presence, as given)",
    "roslab/reporting/summary.py::RunSummary.record": "a failed host's roster path, where its settings may not build",
    "roslab/reporting/summary.py::secrets_in": "every secret value a host's data holds, to mask it in the output",
    "roslab/ros/rosdep_data.py::for_distro": "a download's bytes, not a host's data",
    "roslab/sources/groups.py::check_underlay_builders": "the roster's value as given, before settings are built",
    "roslab/ssh/run_lock.py::lock_problem": "pyinfra's own _sudo_password argument, no roslab setting",
    "roslab/roster/model.py::Host.settings": "builds the host's typed settings from its mapping, once",
    "roslab/roster/model.py::Host.set_data": "what the loader adds after reading, into the mapping pyinfra gets",
    "roslab/roster/inventory.py::inventory_groups": "hands each host's mapping to pyinfra as its host data",
    "roslab/roster/reader.py::RosterReader.check_command_line": "compares the mapping with what pyinfra's --data "
                                                                "puts on top of it, as given",
    "roslab/roster/checks.py::check_host": "roslab.host_rules judges the mapping, as it judges a hand-made "
                                           "inventory's before any settings are built",
}


def host_mapping_reads(tree: ast.AST) -> list[tuple[str, int, str]]:
    """(function, line, expression) of each `<x>.data` (a host's mapping: `host.data`,
    `self.data`, `hosts[0].data.get(...)`); a call's `.data` (a download's bytes) is not a host's. `function`: `Class.method`, `function`, or "" at module level."""
    found: list[tuple[str, int, str]] = []

    def visit(node: ast.AST, scope: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = f"{scope}.{child.name}" if scope else child.name
                # a function's helpers count as the function (check_host's own closures)
                visit(child, scope if isinstance(child, ast.FunctionDef) and scope and
                      not isinstance(node, ast.ClassDef) else inner)
                continue
            if isinstance(child, ast.Attribute) and child.attr == "data" and not isinstance(child.value, ast.Call):
                found.append((scope, child.lineno, ast.unparse(child)))
            visit(child, scope)

    visit(tree, "")
    return found


def test_roster_status_and_verify_read_a_hosts_settings_typed():
    paths = sorted(ROOT.rglob("*.py"))
    reads = {f"{path.relative_to(CHECKOUT)}::{scope}": (line, expression)
             for path in paths for scope, line, expression in host_mapping_reads(ast.parse(path.read_text()))}
    assert {place: read for place, read in reads.items() if place not in MAPPING_BOUNDARY} == {}
    assert set(MAPPING_BOUNDARY) - set(reads) == set(), "a boundary that no longer reads the mapping leaves the list"


def test_the_mapping_rule_sees_each_read_and_where_it_is():
    source = ("class Host:\n    def settings(self):\n        return of(self.data)\n"
              "def f(host):\n    return host.data.get('k')\n"
              "def g(classroom):\n    def inner(h):\n        return h.data['k']\n    return [inner(h) for h in classroom.hosts]\n"
              "def h(url):\n    return kept(url).data, host.settings.ros_distro, hosts[0].data\n")
    assert [(scope, line) for scope, line, _ in host_mapping_reads(ast.parse(source))] == [
        ("Host.settings", 3), ("f", 5), ("g", 8), ("h", 11)]
