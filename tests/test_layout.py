"""The layout rules (docs/layout.md): a stage module imports libraries only, never another stage, and a
library never imports a stage, so that editing one stage reruns only the stages downstream of it; stages
declare the inputs they read; each file two stages hand over has one owner (its record); modules stay small;
tests share one definition of each fixture and path."""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

from stages.app.pipeline import STAGES
from stages.contract.inputs import Inputs
from stages.engine.cache_keys import stages_imports

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = {stage.module for stage in STAGES.values()}
APP_MODULES = {"stages.app.config", "stages.app.pipeline", "stages.app.preflight"}  # the app: stages into a graph, its inputs checked


def project_modules() -> dict[str, set[str]]:
    """Every module under stages/ with the `stages.*` modules it imports."""
    modules = {}
    for path in sorted((ROOT / "stages").rglob("*.py")):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        modules[name] = stages_imports(name, path.read_text())
    return modules


def test_stages_and_libraries_import_no_stage():
    offenders = {name: sorted(imported & STAGE_MODULES - {name})
                 for name, imported in project_modules().items() if name not in APP_MODULES}
    assert {name: found for name, found in offenders.items() if found} == {}


def imported_modules(path: Path) -> set[str]:
    """Names of the modules a Python file imports."""
    tree = ast.parse(path.read_text())
    imported = {node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    return imported | {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}


def test_tests_import_no_test_module():
    """Shared builders live in tests/factories/, never in a test module another test imports."""
    offenders = {}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        found = sorted(name for name in imported_modules(path) if name.split(".")[-1].startswith("test_"))
        if found:
            offenders[str(path.relative_to(ROOT))] = found
    assert offenders == {}


def test_benchmarks_share_the_factories_and_leave_sys_path_alone():
    """Benchmarks run as `python -m benchmarks.<name>`: from tests they import tests.factories only, and
    none edits sys.path."""
    offenders = {}
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        wrong = sorted(name for name in imported_modules(path)
                       if name.startswith("tests") and not name.startswith("tests.factories"))
        wrong += ["sys.path edit"] if "sys.path" in path.read_text() else []
        if wrong:
            offenders[path.name] = wrong
    assert offenders == {}


MAX_MODULE_LINES = 400


def test_no_module_is_over_400_lines():
    """Small modules with one job each (docs/layout.md)."""
    long = {str(path.relative_to(ROOT)): lines for folder in ("stages", "benchmarks") for path in (ROOT / folder).rglob("*.py")
            if (lines := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}


def read_input_names(module_path: Path) -> set[str]:
    """The string literals a module reads as `ctx.inputs[...]`, `ctx.inputs.get(...)` or `"..." in ctx.inputs`."""
    names = set()
    for node in ast.walk(ast.parse(module_path.read_text())):
        target = None
        if isinstance(node, ast.Subscript):
            target, key = node.value, node.slice
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
            target, key = node.func.value, node.args[0] if node.args else None
        elif isinstance(node, ast.Compare) and isinstance(node.ops[0], ast.In):
            target, key = node.comparators[0], node.left
        if (isinstance(target, ast.Attribute) and target.attr == "inputs" and isinstance(key, ast.Constant)
                and isinstance(key.value, str)):
            names.add(key.value)
    return names


def test_every_stage_declares_the_inputs_it_reads():
    """A stage module's INPUTS (stages/contract/inputs.py) names every input its code reads; the engine refuses others."""
    undeclared = {}
    for stage in STAGES.values():
        spec = importlib.import_module(f"stages.{stage.name}.spec")
        assert isinstance(spec.INPUTS, Inputs) and stage.inputs is spec.INPUTS
        read = read_input_names(Path(importlib.import_module(stage.module).__file__))
        missing = sorted(name for name in read if stage.inputs.find(name) is None)
        if missing:
            undeclared[stage.name] = missing
    assert undeclared == {}


def file_name_literals(path: Path) -> set[str]:
    """The strings of a module's code that name a file (a literal, or an f-string part, ending in /name),
    not its docstrings or messages."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr)}
    return {node.value.rsplit("/", 1)[-1] for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings
            and " " not in node.value}


def test_the_files_of_the_records_are_spelled_only_in_their_records():
    """One owner per hand-off: the file names a record reads and writes appear nowhere else in stages/."""
    owned = {}
    for path in sorted((ROOT / "stages" / "records").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.AnnAssign) and isinstance(node.value, ast.Constant) and "ClassVar" in ast.unparse(
                    node.annotation) and "." in str(node.value.value):
                owned[node.value.value] = path.name
    assert {"sfm.json", "annotations.json", "frames.json", "depth.json", "planes.json", "extract.json"} <= set(owned)
    spelled = {}
    for path in sorted((ROOT / "stages").rglob("*.py")):
        if path.parent.name == "records":
            continue
        found = sorted(name for name in owned if name in file_name_literals(path))
        if found:
            spelled[str(path.relative_to(ROOT))] = found
    assert spelled == {}


def test_one_definition_of_the_real_captures_path_and_of_each_shared_fixture():
    """The real captures' path lives in tests/factories/configs.py, fixtures shared by modules in conftest.py."""
    offenders = {}
    for path in sorted((ROOT / "tests").rglob("*.py")) + sorted((ROOT / "benchmarks").rglob("*.py")):
        if path.name == "test_layout.py":
            continue
        text = path.read_text()
        if '"shared" / "real"' in text and path.relative_to(ROOT) != Path("tests/factories/configs.py"):
            offenders[str(path.relative_to(ROOT))] = "defines the real captures' path"
        if path.name != "conftest.py" and ("def one_thread(" in text or "def real(" in text):
            offenders[str(path.relative_to(ROOT))] = "defines a conftest fixture again"
    assert offenders == {}
