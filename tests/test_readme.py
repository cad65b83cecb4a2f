"""README.md as a new user reads it (issue 57): short, the two commands of a fresh machine first, the DAG near the
top, no clock times, every relative link resolving, and every command line in its code blocks either run here (the
cheap ones: --help, plan, graph, gc, each in a temporary folder with a temporary cache) or listed below with the
reason it is not (the heavy ones; those of dag.py are still planned, which checks their settings and inputs)."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

INSTALL_AND_RUN = "python3 -m venv .venv && . .venv/bin/activate && ./install.sh && python dag.py"
TEST_COMMAND = "python -m pytest -q"  # .ci/run runs ./install.sh, then this

# Commands of the README's code blocks that are not run as written here: the reason, and for a dag.py command the
# settings with which it is planned instead (`run.action=plan` and these; None: not planned). A plan opens every
# input and checks every setting in seconds; a sweep is planned at one of its points.
HEAVY = {
    TEST_COMMAND: ("the whole test suite: this test is part of it", None),
    "python dag.py run.until=extract": ("trains the five object models (about 10 minutes on 2 cores)", ""),
    "python dag.py variant=no_placement": ("a whole run of another variant (about half an hour on 2 cores)", ""),
    "python dag.py +experiment=ablation": ("the paper's ablation: 12 jobs, hours on 2 cores", "variant=full run.seed=0"),
    "python dag.py +experiment=smoke": ("the whole DAG on a tiny setting: minutes (tests/test_dag_smoke.py runs it)", ""),
    "python dag.py data=my_data.yaml run.action=plan": ("needs your data file and the files it names", None),
    "python dag.py data=my_data.yaml": ("needs your data file and the files it names", None),
    "python dag.py run.action=predict predict.source=my_photos/": ("needs the trained detector and your photos "
                                                                   "(tests/test_predict_dag.py runs it)", None),
    "python dag.py run.action=predict predict.export=my_detector": ("needs the trained detector "
                                                                    "(tests/test_predict_dag.py runs it)", None),
    "python -m stages.app.predict my_detector kitchen.mp4": ("needs a model folder and your video "
                                                         "(tests/test_predict.py runs it)", None),
    "python -m stages.app.dataset_card FOLDER": ("needs a COCO folder (tests/test_dataset_card.py runs it)", None),
}
CHEAP_DAG = ("--help", "run.action=plan", "run.action=graph", "run.action=gc", "run.action=verify")
CLOCK_TIME = re.compile(r"(?<![\d.:])(?:[01]?\d|2[0-3]):[0-5]\d(?![\d.])")  # 07:21, 7:21-7:31; not 0.50:0.95
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
# The documents issue 57 wrote or moved: their relative links must resolve too.
DOCUMENTS = [README, ROOT / "BENCHMARKS.md",
             *(ROOT / "docs" / f"{name}.md" for name in ("own_data", "background_depth", "running", "experiments",
                                                        "dataset_formats", "gpu_and_cluster", "reproducibility")),
             *(ROOT / "benchmarks" / "results" / f"{name}.md" for name in (
                 "default_run", "ablation", "engine", "gpu", "slurm", "replay", "determinism", "mono_depth/history",
                 "captures/history", "startup/history", "convert/history"))]


def code_blocks(text: str) -> list[tuple[int, str, list[str]]]:
    """(line number of the opening fence, language, lines) of every fenced block."""
    blocks, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"```(\w*)\s*$", lines[i])
        if fence:
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            blocks.append((i + 1, fence.group(1), lines[i + 1:end]))
            i = end
        i += 1
    return blocks


def commands(text: str) -> list[str]:
    """The `python dag.py ...` and `python -m ...` command lines of the shell blocks, continuation lines joined and
    comments dropped."""
    found = []
    for _, language, lines in code_blocks(text):
        if language not in ("bash", "sh", "shell", ""):
            continue
        joined = re.sub(r"\\\n\s*", " ", "\n".join(lines))
        for line in joined.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line.startswith(("python dag.py", "python -m ")):
                found.append(" ".join(line.split()))
    return found


def is_cheap(command: str) -> bool:
    words = command.split()
    if command.startswith("python dag.py"):
        return any(word in CHEAP_DAG for word in words[2:])
    return words[-1] == "--help"


def run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """`command` as a process in `cwd`: dag.py from this checkout with its cache in `cwd`, a module importable from
    it."""
    words = shlex.split(command)
    if words[:2] == ["python", "dag.py"]:
        argv = [sys.executable, str(ROOT / "dag.py"), *words[2:]]
        if "--help" not in words:
            argv.append(f"run.cache_dir={cwd / 'cache'}")
    else:
        argv = [sys.executable, *words[1:]]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


README_TEXT = README.read_text()
README_COMMANDS = list(dict.fromkeys(commands(README_TEXT)))


def test_the_readme_is_short():
    assert len(README_TEXT.splitlines()) < 200


def test_the_two_commands_of_a_fresh_machine_come_first():
    (first_line, _, first), (second_line, _, second) = code_blocks(README_TEXT)[:2]
    assert first == [INSTALL_AND_RUN] and second == [TEST_COMMAND]
    assert second_line + len(second) + 1 <= 40  # both blocks, closing fences included, within the first 40 lines
    assert TEST_COMMAND in (ROOT / ".ci" / "run").read_text() and "./install.sh" in (ROOT / ".ci" / "run").read_text()


def test_the_dag_is_drawn_within_the_first_60_lines():
    start, _, lines = next(block for block in code_blocks(README_TEXT) if block[1] == "mermaid")
    assert start + len(lines) + 1 <= 60, "the mermaid block ends after line 60"


def test_no_clock_times():
    found = [(number, line) for number, line in enumerate(README_TEXT.splitlines(), 1) if CLOCK_TIME.search(line)]
    assert not found


def github_anchor(heading: str) -> str:
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda path: str(path.relative_to(ROOT)))
def test_relative_links_resolve(document):
    broken = []
    for target in LINK.findall(document.read_text()):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (document.parent / path).resolve() if path else document
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md":
            headings = re.findall(r"^#+ (.+)$", file.read_text(), re.M)
            if anchor not in {github_anchor(h) for h in headings}:
                broken.append(target)
    assert not broken, f"{document.name}: {broken}"


def test_every_command_is_run_or_listed():
    assert len(README_COMMANDS) >= 8
    unaccounted = [c for c in README_COMMANDS if c not in HEAVY and not is_cheap(c)]
    assert not unaccounted, "run it in test_cheap_commands_run or list it in HEAVY with a reason"
    stale = [c for c in HEAVY if c not in README_COMMANDS]
    assert not stale, "no longer in the README: remove from HEAVY"


@pytest.mark.parametrize("command", [c for c in README_COMMANDS if c not in HEAVY and is_cheap(c)])
def test_cheap_commands_run(command, tmp_path):
    done = run(command, tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]


@pytest.mark.parametrize("command, settings", [(c, plan) for c, (_, plan) in HEAVY.items() if plan is not None])
def test_heavy_dag_commands_plan(command, settings, tmp_path):
    done = run(f"{command} run.action=plan {settings}", tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
