"""Cache keys change only when behaviour can: the code hash is of syntax trees, not of source text."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from stages.app.pipeline import STAGES
from stages.engine.cache_keys import module_closure, normalised_source, stages_imports

ROOT = Path(__file__).resolve().parents[1]
STAGE_MODULES = sorted({stage.module for stage in STAGES.values()})

CODE = textwrap.dedent('''
    """Module docstring."""
    import math


    def area(r):  # a comment
        """Docstring."""
        return math.pi * r ** 2
''')


def test_comments_docstrings_and_formatting_do_not_count():
    edited = textwrap.dedent('''
        """Another module docstring, longer.

        With a second paragraph."""
        import math

        # a new comment line


        def area(r):
            "Another docstring."
            "a bare string statement"
            return math.pi * r**2   # reformatted
    ''')
    assert normalised_source(edited) == normalised_source(CODE)


@pytest.mark.parametrize("change", [("math.pi * r ** 2", "math.pi * r ** 3"), ("def area(r)", "def area(radius)"),
                                    ("return", "x = 'Docstring.'\n    return")])
def test_code_edits_count(change):
    assert normalised_source(CODE.replace(*change)) != normalised_source(CODE)


def test_type_checking_imports_are_not_followed():
    source = textwrap.dedent("""
        from typing import TYPE_CHECKING
        from stages.lib.geometry import look_at_point
        if TYPE_CHECKING:
            from stages.engine.context import Context
        else:
            from stages.lib.imageio import load_photo
    """)
    assert stages_imports("stages.x", source) == {"stages", "stages.lib", "stages.lib.geometry",
                                                  "stages.lib.geometry.look_at_point", "stages.lib.imageio",
                                                  "stages.lib.imageio.load_photo"}


def test_no_stage_reaches_the_engine():
    """A stage's key holds its own code and its libraries', never the engine's (Context, StageError's home)."""
    assert {m: sorted(n for n in module_closure(m) if n.startswith("stages.engine")) for m in STAGE_MODULES} == {
        m: [] for m in STAGE_MODULES}


def code_hashes(root: Path) -> dict[str, str]:
    """{stage module: code hash} computed by a fresh Python whose `stages` package is the one under root."""
    program = ("import json; from stages.engine.cache_keys import module_closure_hash; "
               f"print(json.dumps({{m: module_closure_hash(m) for m in {STAGE_MODULES!r}}}))")
    done = subprocess.run([sys.executable, "-c", program], cwd=root, capture_output=True, text=True, check=True,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})
    return json.loads(done.stdout)


@pytest.fixture
def package_copy(tmp_path):
    """A copy of the stages package to edit."""
    shutil.copytree(ROOT / "stages", tmp_path / "stages", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    return tmp_path


def test_a_docstring_edit_keeps_every_key_and_a_code_edit_rekeys_exactly_its_stages(package_copy):
    before = code_hashes(package_copy)
    library = package_copy / "stages" / "lib" / "geometry.py"
    source = library.read_text()
    library.write_text('"""A rewritten docstring."""\n# and a comment\n' + source.split('"""', 2)[2])
    assert code_hashes(package_copy) == before

    library.write_text(source + "\n_UNUSED_CONSTANT = 1\n")
    after = code_hashes(package_copy)
    reaching = {m for m in STAGE_MODULES if "stages.lib.geometry" in module_closure(m)}
    assert 0 < len(reaching) < len(STAGE_MODULES)  # the check below tells reaching stages from the others
    assert {m for m in STAGE_MODULES if after[m] != before[m]} == reaching


def test_a_kernel_edit_rekeys_the_stages_that_build_the_kernels_and_no_other(package_copy):
    before = code_hashes(package_copy)
    kernel = package_copy / "stages" / "lib" / "gaussians" / "csrc" / "loss.cpp"
    kernel.write_text(kernel.read_text() + "\n// an edit\n")
    after = code_hashes(package_copy)
    building = {m for m in STAGE_MODULES if "stages.lib.gaussians.native" in module_closure(m)}
    assert "stages.splat_train.run" in building
    assert "stages.sfm.run" not in building and "stages.lib.gaussians.colmap" in module_closure("stages.sfm.run")
    assert {m for m in STAGE_MODULES if after[m] != before[m]} == building
