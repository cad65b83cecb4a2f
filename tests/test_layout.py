"""The layout rules (docs/layout.md), by folder: imports go down the folders of stages/ (app, a stage's room,
engine, lib and records, contract), never up and never in a circle, type-only imports included, so that editing
one stage reruns only the stages downstream of it; specs load nothing heavy; nothing test-only ships; stages
declare the inputs they read; each file two stages hand over has one owner (its record); modules stay small in
small folders; tests share one definition of each fixture and path."""
from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
from pathlib import Path

from stages.app.pipeline import STAGES
from stages.contract.inputs import Inputs

from stages.app.pipeline import STAGES
from stages.contract.inputs import Inputs
from stages.engine.cache_keys import module_closure, stages_imports

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = {stage.module for stage in STAGES.values()}
# What each folder of stages/ may import (docs/layout.md). A stage's room (stages/<stage>/) imports its own room
# only; records and lib are the libraries (records.sfm reads COLMAP through lib.gaussians, lib reads records).
MAY_IMPORT = {
    "contract": {"contract"},
    "records": {"contract", "records", "lib"},
    "lib": {"contract", "lib", "records"},
    "room": {"contract", "lib", "records", "room"},
    "engine": {"contract", "engine", "lib"},
    "app": {"contract", "lib", "records", "engine", "room", "app"},
}
HEAVY = ("torch", "cv2", "open3d", "pycolmap")
MAX_MODULE_LINES = 400
MAX_FOLDER_MODULES = 18


def module_name(path: Path) -> str:
    """The dotted name of a module under ROOT (a package by its folder's name)."""
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def folder(module: str) -> str:
    """The folder role of a `stages.*` module: "room" for a stage's, else the folder under stages/ ("" for the
    package itself)."""
    parts = module.split(".")
    if len(parts) == 1:
        return ""
    return "room" if parts[1] in STAGES else parts[1]


def project_modules() -> dict[str, Path]:
    """{name: file} of every module under stages/."""
    return {module_name(path): path for path in sorted((ROOT / "stages").rglob("*.py"))}


def all_imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The `stages.*` modules (and the packages that hold them) a module imports, those under `if TYPE_CHECKING:`
    included: stages_imports of its source with that guard read as `if True:`."""
    key = f"{name}.__init__" if path.name == "__init__.py" else name
    source = path.read_text().replace("if TYPE_CHECKING:", "if True:")
    return {module for module in stages_imports(key, source) if module in modules and module != name}


def import_graph() -> dict[str, set[str]]:
    """{module: the stages.* modules it imports (type-only imports included)} of every module under stages/."""
    modules = project_modules()
    return {name: all_imports(name, path, modules) for name, path in modules.items()}


def test_each_folder_imports_only_the_folders_below_it():
    """The import direction between the folders (type-only imports included): the app imports the stages' specs,
    the engine, the libraries and the contract; the engine the contract and libraries; a stage its own room, the
    libraries and the contract; a library libraries and the contract; the contract itself only."""
    graph, runtime = import_graph(), {name: stages_imports(name, path.read_text())
                                      for name, path in project_modules().items()}
    wrong = {}
    for name, imported in graph.items():
        role = folder(name)
        for module in sorted(imported):
            target = folder(module)
            type_only_context = (role == "room" and module in ("stages.engine", "stages.engine.context")
                                 and module not in runtime[name])
            other_room = role == "room" and target == "room" and module.split(".")[1] != name.split(".")[1]
            a_stage_run = role == "app" and target == "room" and module.split(".")[2:] not in ([], ["spec"])
            refused = target not in MAY_IMPORT.get(role, set()) or other_room or a_stage_run
            if target and refused and not type_only_context:
                wrong.setdefault(name, []).append(module)
    assert wrong == {}


def test_no_import_circle():
    """No module reaches itself through imports, type-only ones included."""
    graph = import_graph()
    circles = []
    for start in graph:
        todo, seen = list(graph[start]), set()
        while todo:
            current = todo.pop()
            if current == start:
                circles.append(start)
                break
            if current not in seen:
                seen.add(current)
                todo.extend(graph.get(current, ()))
    assert circles == []


def test_no_stage_imports_another_stage():
    """A stage's key holds its own room's code and the libraries', so an edit re-keys only the stages it reaches."""
    offenders = {module: sorted(name for name in module_closure(module)
                                if folder(name) == "room" and name.split(".")[1] != module.split(".")[1])
                 for module in STAGE_MODULES}
    assert {module: found for module, found in offenders.items() if found} == {}


def test_specs_load_nothing_heavy():
    """The app composes and checks a config from the specs without torch, OpenCV, Open3D or COLMAP (a fresh
    Python's sys.modules after importing every spec)."""
    specs = sorted(f"stages.{name}.spec" for name in STAGES)
    program = (f"import sys, importlib; [importlib.import_module(m) for m in {specs!r}]; "
               f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", program], cwd=ROOT, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def shipped_names() -> set[str]:
    """Every name shipped code (stages/ and dag.py) uses: names, attributes, imported names and `module:function`."""
    used = set()
    for path in sorted((ROOT / "stages").rglob("*.py")) + [ROOT / "dag.py"]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Name):
                used.add(node.id)
            elif isinstance(node, ast.Attribute):
                used.add(node.attr)
            elif isinstance(node, ast.alias):
                used.update({node.name.rpartition(".")[2], node.asname or ""})
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and ":" in node.value:
                used.add(node.value.rpartition(":")[2])
    return used


def test_nothing_test_only_ships_in_a_stage():
    """Every public function and class of the code a stage's key holds is used by shipped code: what only tests
    use lives in tests/factories/."""
    used = shipped_names()
    keyed = {path for module in STAGE_MODULES for path in module_closure(module).values()}
    unused = {str(path.relative_to(ROOT)): sorted(node.name for node in ast.parse(path.read_text()).body
                                                   if isinstance(node, (ast.FunctionDef, ast.ClassDef))
                                                   and not node.name.startswith("_") and node.name not in used)
              for path in sorted(keyed)}
    assert {path: names for path, names in unused.items() if names} == {}


def test_every_module_is_shipped_code():
    """Each module under stages/ is a package, a stage's run, an app command or imported by another module, by
    dag.py or by conf/ (a Hydra `_target_`)."""
    graph, modules = import_graph(), project_modules()
    targets = {line.split(":", 1)[1].strip().rpartition(".")[0] for path in (ROOT / "conf").rglob("*.yaml")
               for line in path.read_text().splitlines() if line.strip().startswith("_target_:")}
    imported = set().union(*graph.values(), all_imports("dag", ROOT / "dag.py", modules), targets)
    commands = {name for name, path in project_modules().items() if "__main__" in path.read_text()}
    lonely = sorted(name for name, path in project_modules().items() if path.name != "__init__.py"
                    and name not in imported | commands | STAGE_MODULES)
    assert lonely == []


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


# The benchmark modules tests import: the libraries (benchmarks/lib/) and the scripts whose own parts tests check
# (their report, their scoring; the CLI test runs every script's main through the package); a new one is added here
# on purpose.
BENCHMARKS_TESTS_IMPORT = {"benchmarks", "benchmarks.lib.cut_scoring", "benchmarks.lib.cutout_boxes",
                           "benchmarks.lib.evaluation", "benchmarks.lib.truth_views", "benchmarks.captures",
                           "benchmarks.class_gap", "benchmarks.convert", "benchmarks.inference_size",
                           "benchmarks.mask_ceiling", "benchmarks.mask_refinement", "benchmarks.rendered_training",
                           "benchmarks.replay", "benchmarks.supersampling", "benchmarks.walk_backgrounds",
                           "benchmarks.lib.opensplat_build", "benchmarks.lib.splat_runs", "benchmarks.opensplat",
                           "benchmarks.gpu_job", "benchmarks.wall_capture", "benchmarks.dataset_size",
                           "benchmarks.lib.settings", "benchmarks.antialiased_splats"}


def test_tests_import_only_the_listed_benchmark_modules():
    imported = {name for path in (ROOT / "tests").rglob("*.py") for name in imported_modules(path)
                if name.split(".")[0] == "benchmarks"}
    assert imported - BENCHMARKS_TESTS_IMPORT == set()
    assert {name for name in BENCHMARKS_TESTS_IMPORT if name != "benchmarks"
            and not (ROOT / (name.replace(".", "/") + ".py")).is_file()} == set()  # no stale entry


def test_benchmark_scripts_import_libraries_not_one_another():
    """benchmarks/<name>.py are scripts (a main, run as python -m); benchmarks/lib/ holds what they share. A script
    imports benchmarks.lib.* only, a library no script and has no main."""
    scripts = {f"benchmarks.{path.stem}" for path in (ROOT / "benchmarks").glob("*.py") if path.stem != "__init__"}
    offenders = {}
    for path in sorted((ROOT / "benchmarks").rglob("*.py")):
        wrong = sorted(name for name in imported_modules(path) if name in scripts)
        if path.parent.name == "lib" and re.search(r"^def main\(", path.read_text(), re.MULTILINE):
            wrong.append("a main")
        if wrong:
            offenders[str(path.relative_to(ROOT))] = wrong
    assert offenders == {}
    assert all(re.search(r"^def main\(", (ROOT / (name.replace(".", "/") + ".py")).read_text(), re.MULTILINE)
               for name in scripts)  # every module of benchmarks/ outside lib/ is a script


def test_benchmarks_share_the_factories_and_leave_sys_path_alone():
    """Benchmarks run as `python -m benchmarks.<name>`: from tests they import tests.factories only, and
    none edits sys.path."""
    offenders = {}
    for path in sorted((ROOT / "benchmarks").rglob("*.py")):
        wrong = sorted(name for name in imported_modules(path)
                       if name.startswith("tests") and not name.startswith("tests.factories"))
        wrong += ["sys.path edit"] if "sys.path" in path.read_text() else []
        if wrong:
            offenders[path.name] = wrong
    assert offenders == {}


def test_small_modules_in_small_folders():
    """Small modules with one job each, at most 400 lines (stages/ and benchmarks/), and at most 18 modules in a
    folder of stages/ (docs/layout.md)."""
    long = {str(path.relative_to(ROOT)): lines for top in ("stages", "benchmarks")
            for path in (ROOT / top).rglob("*.py") if (lines := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    crowded = {str(path.relative_to(ROOT)): count for path in (ROOT / "stages").rglob("*") if path.is_dir()
               and (count := len([m for m in path.glob("*.py") if m.name != "__init__.py"])) > MAX_FOLDER_MODULES}
    assert (long, crowded) == ({}, {})


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
    """A stage's INPUTS (stages/contract/inputs.py) names every input its run reads; the engine refuses others."""
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
