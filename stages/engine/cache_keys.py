"""What a cache key is made of: the code a stage runs, its inputs' contents, canonical JSON and seeds.

A stage's code hash covers its module and every `stages.*` module it imports, recursively (with the
packages that hold them, whose `__init__` runs first), plus the native sources (`csrc/`) of the modules that
build them (a module that names its `csrc` folder: stages/lib/gaussians/native.py), so that a kernel edit re-keys
the stages that run the kernels and not those that only read a COLMAP model from the same package. Each
module enters as its normalised syntax tree, not its text: comments, docstrings and other bare string
statements, blank lines and formatting do not change a key; anything that can change behaviour does.
Imports under `if TYPE_CHECKING:` run only for type checkers and are not followed (stages import the
engine's `Context` that way). `Stage.version` (stages/engine/scheduler.py) is the deliberate way to re-key a stage
whose code did not change (e.g. when a dependency's behaviour changed).
"""
from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
from functools import lru_cache
from pathlib import Path
from typing import Any

from stages.contract.errors import StageError

PACKAGE = "stages"
NATIVE_FOLDER = "csrc"


def sha256_hex(data: bytes) -> str:
    """The sha256 hex digest of `data`."""
    return hashlib.sha256(data).hexdigest()


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: equal configs give equal strings."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


def derive_seed(global_seed: int, stage: str, item: str) -> int:
    """A 31-bit seed from (global seed, stage, item): independent of worker count and order."""
    return int(sha256_hex(f"{global_seed}/{stage}/{item}".encode())[:8], 16) & 0x7FFFFFFF


# ------------------------------------------------------------------------------------------- code

@lru_cache(maxsize=None)
def _package_root() -> Path:
    """The folder of the `stages` package in use (found without importing any of its modules)."""
    return Path(importlib.util.find_spec(PACKAGE).origin).parent


def _module_file(name: str) -> Path | None:
    """The source file of a module, or None for names that are not modules (e.g. `pkg.mod.Class`). A `stages.*`
    module is found on disk without importing it (importing a library only to hash it would load torch for a
    plan); another module (a stage defined elsewhere) through its import spec."""
    parts = name.split(".")
    if parts[0] != PACKAGE:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            return None
        return Path(spec.origin) if spec is not None and spec.origin and spec.origin.endswith(".py") else None
    folder = _package_root().joinpath(*parts[1:])
    for path in ([folder.with_suffix(".py")] if len(parts) > 1 else []) + [folder / "__init__.py"]:
        if path.is_file():
            return path
    return None


@lru_cache(maxsize=None)
def _parsed(name: str, path: Path) -> tuple[frozenset[str], str, bool]:
    """The `stages.*` imports and the normalised code of one module, and whether it names the `csrc` folder of
    native sources beside it (memoised like the closure hashes)."""
    source = path.read_text()
    tree = ast.parse(source)
    builds_native = any(isinstance(node, ast.Constant) and node.value == NATIVE_FOLDER for node in ast.walk(tree))
    return frozenset(_imports_of(name, tree)), _canonical_tree(tree), builds_native


def _is_type_checking_block(node: ast.AST) -> bool:
    """True for `if TYPE_CHECKING:` / `if typing.TYPE_CHECKING:` (imports for type checkers only)."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node of `tree` outside `if TYPE_CHECKING:` blocks (their `else` branches are kept)."""
    found, todo = [], [tree]
    while todo:
        node = todo.pop()
        found.append(node)
        if _is_type_checking_block(node):
            todo.extend(node.orelse)
            continue
        todo.extend(ast.iter_child_nodes(node))
    return found


def stages_imports(name: str, source: str) -> set[str]:
    """Names of `stages.*` modules a module's source imports at run time (absolute and relative imports,
    with the packages that hold them); imports under `if TYPE_CHECKING:` are not counted."""
    return _imports_of(name, ast.parse(source))


def _imports_of(name: str, tree: ast.AST) -> set[str]:
    """stages_imports of a parsed module."""
    package = name if name.endswith("__init__") else name.rpartition(".")[0]
    found: set[str] = set()
    for node in _runtime_nodes(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    parents = {name.rsplit(".", depth)[0] for name in found for depth in range(1, name.count(".") + 1)}
    return {n for n in found | parents if n == PACKAGE or n.startswith(PACKAGE + ".")}


def _is_bare_string(node: ast.AST) -> bool:
    """A statement that is only a string literal: a docstring or another no-op string."""
    return isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)


def _canonical_tree(node: Any) -> str:
    """A text of the syntax tree that omits positions, bare string statements and empty or None fields
    (so that a Python version adding an empty field, e.g. 3.12's `type_params`, gives the same text)."""
    if isinstance(node, ast.AST):
        parts = []
        for name in node._fields:
            value = getattr(node, name, None)
            if isinstance(value, list):
                value = [item for item in value if not _is_bare_string(item)]
            if value is None or value == []:
                continue
            parts.append(f"{name}={_canonical_tree(value)}")
        return f"{type(node).__name__}({','.join(parts)})"
    if isinstance(node, list):
        return "[" + ",".join(_canonical_tree(item) for item in node) + "]"
    return f"{type(node).__name__}:{node!r}"


def normalised_source(source: str) -> str:
    """The module's behaviour as text: its syntax tree without comments, docstrings or formatting."""
    return _canonical_tree(ast.parse(source))


def module_closure(name: str) -> dict[str, Path]:
    """{module name: source file} of a module and every `stages.*` module it imports, recursively."""
    seen: dict[str, Path] = {}
    todo = [name]
    while todo:
        current = todo.pop()
        path = None if current in seen else _module_file(current)
        if path is None:
            continue
        seen[current] = path
        todo.extend(_parsed(current, path)[0])
    return seen


@lru_cache(maxsize=None)
def module_closure_hash(name: str) -> str:
    """Hash of the normalised code of `module_closure(name)`, and of the native sources those modules build."""
    closure = module_closure(name)
    digest = hashlib.sha256()
    for mod in sorted(closure):
        _, code, builds_native = _parsed(mod, closure[mod])
        digest.update(mod.encode() + b"\0" + code.encode())
        native = closure[mod].parent / NATIVE_FOLDER
        for src in sorted(native.rglob("*")) if builds_native and native.is_dir() else []:
            if src.is_file():
                digest.update(str(src.relative_to(native)).encode() + b"\0" + src.read_bytes())
    return digest.hexdigest()


# ----------------------------------------------------------------------------------------- inputs

@lru_cache(maxsize=4096)
def _file_hash(path: str, size: int, mtime_ns: int) -> str:
    """Content hash of one file (memoised on size and mtime within a process; never keyed on them)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def content_hash(path: Path) -> str:
    """Hash of a raw input's content: a file's bytes, or a folder's relative names and file bytes."""
    if not path.exists():
        raise StageError(f"input not found: {path}")
    if path.is_file():
        stat = path.stat()
        return _file_hash(str(path), stat.st_size, stat.st_mtime_ns)
    digest = hashlib.sha256()
    for child in sorted(p for p in path.rglob("*") if p.is_file()):
        stat = child.stat()
        digest.update(str(child.relative_to(path)).encode() + b"\0")
        digest.update(_file_hash(str(child), stat.st_size, stat.st_mtime_ns).encode())
    return digest.hexdigest()


def forget_hashes() -> None:
    """Drop this process's memoised code and file hashes (as in a fresh process; tests and benchmarks)."""
    module_closure_hash.cache_clear()
    _parsed.cache_clear()
    _file_hash.cache_clear()
