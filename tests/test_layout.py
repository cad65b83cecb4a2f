"""The layout rule (docs/layout.md): a stage module imports libraries only, never another stage, and a
library never imports a stage, so that editing one stage reruns only the stages downstream of it."""
from __future__ import annotations

from pathlib import Path

from stages.engine import stages_imports
from stages.pipeline import STAGES

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = {stage.run.__module__ for stage in STAGES.values()}
APP_MODULES = {"stages.config", "stages.pipeline"}  # the app composes the stages into a graph


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
