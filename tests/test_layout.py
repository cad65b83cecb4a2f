"""The layout rule (docs/layout.md): a stage module imports libraries only, never another stage, and a
library never imports a stage, so that editing one stage reruns only the stages downstream of it."""
from __future__ import annotations

import ast
from pathlib import Path

from stages.cache_keys import stages_imports
from stages.pipeline import STAGES

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = {stage.run.__module__ for stage in STAGES.values()}
APP_MODULES = {"stages.config", "stages.pipeline", "stages.preflight"}  # the app: stages into a graph, its inputs checked


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
