"""Cache entries that can be verified (issue 58): the manifest records each file's size and SHA-256; a cache hit
whose files are missing or of another size is not trusted but computed again, and the run's summary names the
entry and the file; `run.action=verify` reads every entry back, lists the bad ones and (`run.verify_apply=true`)
removes them; entries written before manifests recorded files are trusted until verify records them
(docs/cache.md)."""
from __future__ import annotations

import hashlib
import json
import socket
from pathlib import Path

import pytest

from stages.app.summary import plan_report
from stages.engine.cache_entry import FILES, MANIFEST, key_lock, read_manifest
from stages.engine.cache_verify import verify_cache, verify_report
from stages.engine.scheduler import Engine
from tests.factories.configs import run_dag
from tests.factories.toy_cache import targets


@pytest.fixture
def count_file(tmp_path, monkeypatch):
    path = tmp_path / "count.txt"
    monkeypatch.setenv("TOY_COUNT_FILE", str(path))
    return path


def ran(count_file: Path) -> list[str]:
    return count_file.read_text().split() if count_file.exists() else []


def entries(tmp_path: Path, items: str = "a") -> dict[str, Path]:
    """Run the toy graph for `items` into tmp_path/cache; {label: its entry}."""
    return {r.label: Path(r.path) for r in Engine(tmp_path / "cache").run(targets(items.split(",")))}


def test_the_manifest_records_the_size_and_hash_of_every_file(tmp_path, count_file):
    entry = entries(tmp_path)["payload[a]"]
    files = read_manifest(entry)[FILES]
    assert sorted(files) == ["metrics.json", "payload.bin"]
    for name, recorded in files.items():
        data = (entry / name).read_bytes()
        assert recorded == {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}


@pytest.mark.parametrize("damage, problem", [
    (lambda path: path.write_bytes(path.read_bytes()[:100]), "file payload.bin is 100 bytes, its manifest says 4096"),
    (lambda path: path.unlink(), "file payload.bin is missing"),
])
def test_a_damaged_entry_is_found_by_the_next_run_and_computed_again(tmp_path, count_file, damage, problem):
    entry = entries(tmp_path)["payload[a]"]
    damage(entry / "payload.bin")
    plan = {r.label: r for r in Engine(tmp_path / "cache").plan(targets(["a"]))}
    assert plan["payload[a]"].status == "would-run" and problem in plan["payload[a]"].distrusted
    assert f"payload[a]: cache entry {entry}: {problem}" in plan_report(list(plan.values()), {}, [], tmp_path / "p")
    again = {r.label: r for r in Engine(tmp_path / "cache").run(targets(["a"]))}
    assert again["payload[a]"].status == "ran" and again["payload[a]"].distrusted == f"cache entry {entry}: {problem}"
    assert again["checksum[a]"].status == "cached"  # its own entry was whole
    assert (entry / "payload.bin").stat().st_size == 4096 and ran(count_file) == ["payload[a]", "checksum[a]",
                                                                                    "payload[a]"]


def test_a_file_changed_in_place_passes_the_size_check_and_fails_verify(tmp_path, count_file):
    entry = entries(tmp_path)["payload[a]"]
    data = bytearray((entry / "payload.bin").read_bytes())
    data[7] ^= 0xFF
    (entry / "payload.bin").write_bytes(bytes(data))
    assert [r.status for r in Engine(tmp_path / "cache").run(targets(["a"]))] == ["cached", "cached"]
    checks = {c.path: c for c in verify_cache(tmp_path / "cache")}
    assert checks[entry].status == "bad"
    assert checks[entry].problems == ["file payload.bin has other contents than when it was written (SHA-256 differs)"]


def legacy(entry: Path) -> None:
    """Make `entry` an entry written before manifests recorded files."""
    manifest = read_manifest(entry)
    del manifest[FILES]
    (entry / MANIFEST).write_text(json.dumps(manifest))


def test_verify_lists_every_bad_entry_and_apply_removes_them(tmp_path, count_file):
    found = entries(tmp_path, "a,b,c,d")
    cache = tmp_path / "cache"
    (found["payload[a]"] / "payload.bin").write_bytes(b"short")  # truncated
    (found["payload[b]"] / "extra.txt").write_text("added by hand")  # a file the manifest does not record
    (found["payload[c]"] / MANIFEST).write_text("{not json")  # a torn manifest
    legacy(found["payload[d]"])
    unfinished = cache / "payload" / "0123456789abcdef0123"  # a folder without manifest
    unfinished.mkdir()
    stale = cache / "payload" / f".fedcba9876543210fedc.tmp-{socket.gethostname()}-{2 ** 22 + 7}"
    stale.mkdir()  # left by a killed run (no such process)
    checks = {c.path: c for c in verify_cache(cache)}
    assert {path: c.status for path, c in checks.items() if c.status != "whole"} == {
        found["payload[a]"]: "bad", found["payload[b]"]: "bad", found["payload[c]"]: "bad",
        found["payload[d]"]: "recorded", unfinished: "bad", stale: "bad"}
    assert checks[found["payload[a]"]].problems == ["file payload.bin is 5 bytes, its manifest says 4096"]
    assert checks[found["payload[b]"]].problems == [
        "file extra.txt is not in its manifest (added after the entry was written)"]
    assert "cannot be read" in checks[found["payload[c]"]].problems[0]
    assert checks[unfinished].problems == ["no manifest.json: it was never completed"]
    report = verify_report(list(checks.values()), 0.1, apply=False)
    assert f"bad {found['payload[a]']}: file payload.bin is 5 bytes" in report
    assert "5 bad (run.verify_apply=true removes them), 1 written before manifests recorded files" in report
    assert FILES in read_manifest(found["payload[d]"])  # recorded once: from now on checked like the others

    removed = verify_cache(cache, apply=True)
    assert sorted(c.path for c in removed if c.removed) == sorted(
        [found["payload[a]"], found["payload[b]"], found["payload[c]"], unfinished, stale])
    assert all(not c.path.exists() for c in removed if c.removed)
    assert {c.status for c in verify_cache(cache)} == {"whole"}
    statuses = {r.label: r.status for r in Engine(cache).run(targets(["a", "b", "c", "d"]))}
    assert statuses == {"payload[a]": "ran", "checksum[a]": "cached", "payload[b]": "ran", "checksum[b]": "cached",
                        "payload[c]": "ran", "checksum[c]": "cached", "payload[d]": "cached", "checksum[d]": "cached"}


def test_an_entry_written_before_manifests_recorded_files_is_trusted_until_verify_records_it(tmp_path, count_file):
    entry = entries(tmp_path)["payload[a]"]
    legacy(entry)
    (entry / "payload.bin").write_bytes(b"short")  # damage no record can show
    assert [r.status for r in Engine(tmp_path / "cache").run(targets(["a"]))] == ["cached", "cached"]
    assert {c.path: c.status for c in verify_cache(tmp_path / "cache")}[entry] == "recorded"
    (entry / "payload.bin").write_bytes(b"shorter")  # damage after the record
    assert [r.status for r in Engine(tmp_path / "cache").run(targets(["a"]))] == ["ran", "cached"]


def test_verify_leaves_an_entry_another_process_computes(tmp_path, count_file):
    entry = entries(tmp_path)["payload[a]"]
    (entry / "payload.bin").write_bytes(b"short")
    with key_lock(tmp_path / "cache", "payload", entry.name):
        checks = {c.path: c for c in verify_cache(tmp_path / "cache", apply=True)}
    assert checks[entry].status == "busy" and entry.exists()


@pytest.mark.slow
def test_dag_verify_lists_the_bad_entries(tmp_path, count_file):
    """`python dag.py run.action=verify` over a cache: exit 1, the bad entry named, verify.json in the run folder
    (run.verify_apply=true removes it: verify_cache(apply=True) above)."""
    entry = entries(tmp_path)["payload[a]"]
    (entry / "payload.bin").write_bytes(b"short")
    done, _ = run_dag("run.action=verify", f"run.cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert done.returncode == 1, done.stderr[-2000:]
    assert f"bad {entry}: file payload.bin is 5 bytes, its manifest says 4096" in done.stdout
    assert "2 cache folders checked" in done.stdout and "1 bad (run.verify_apply=true removes them)" in done.stdout
    verdicts = {Path(c["path"]): c["status"] for c in json.loads((tmp_path / "run" / "verify.json").read_text())}
    assert verdicts[entry] == "bad" and sorted(verdicts.values()) == ["bad", "whole"]
