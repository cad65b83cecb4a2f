"""Files from strangers for the fuzz tests of the file readers (tests/test_fuzz_readers.py).

A case replaces one file of a reader's valid seed folder (tests/factories/fuzz_readers.py) with other bytes, a
folder, nothing, or an unreadable file. `generic_cases` are the named cases every reader gets (zero size, one byte,
truncated, random bytes, wrong magic, a folder, unreadable, missing); `mutations` is the Hypothesis strategy of
mutated seeds: truncations, byte flips, lying header fields (huge declared counts and sizes), spliced chunks,
random bytes, and for JSON files any JSON value (NaN, 10^400, deep nesting) put in place of one of the seed's.
"""
from __future__ import annotations

import json
import random
import struct
from dataclasses import dataclass
from typing import Any, Callable

from hypothesis import strategies as st

HUGE = (2 ** 31, 2 ** 32 + 1, 10 ** 10, 2 ** 62, 2 ** 63 - 1, 2 ** 64 - 1)  # declared counts and sizes that lie
Field = Callable[[bytes, int], bytes]  # writes a declared value (a count, a size) into a file's header


@dataclass(frozen=True)
class Case:
    """One input: the seed folder with `file` replaced by `content`, or by a folder / nothing / an unreadable copy
    (`special`: "folder" | "missing" | "unreadable")."""

    name: str
    file: str
    content: bytes = b""
    special: str = ""


def truncated(data: bytes, at: int) -> bytes:
    """The first `at` bytes."""
    return data[:at]


def flipped(data: bytes, edits: list[tuple[int, int]]) -> bytes:
    """`data` with the byte at each position (modulo its length) set to the value given."""
    out = bytearray(data)
    for position, value in edits:
        if out:
            out[position % len(out)] = value
    return bytes(out)


def spliced(data: bytes, at: int, chunk: bytes) -> bytes:
    """`chunk` inserted at position `at`."""
    return data[:at] + chunk + data[at:]


def generic_cases(file: str, data: bytes) -> list[Case]:
    """The named cases of any reader's file `file` (seed bytes `data`)."""
    rng = random.Random(0)
    return [Case("zero-size file", file, b""), Case("one byte", file, data[:1]),
            Case("truncated to half", file, truncated(data, len(data) // 2)),
            Case("last byte missing", file, truncated(data, len(data) - 1)),
            Case("random bytes of the same size", file, rng.randbytes(len(data))),
            Case("4 KB of random bytes", file, rng.randbytes(4096)),
            Case("wrong magic (first 4 bytes inverted)", file, bytes(b ^ 0xFF for b in data[:4]) + data[4:]),
            Case("the file twice", file, data + data),
            Case("a folder where the file is expected", file, special="folder"),
            Case("unreadable (permissions 000)", file, data, special="unreadable"),
            Case("missing", file, special="missing")]


def field_cases(file: str, data: bytes, fields: dict[str, Field]) -> list[Case]:
    """Each header field of `file` made to declare each of HUGE."""
    return [Case(f"{name} = {value}", file, field(data, value)) for name, field in fields.items() for value in HUGE]


JSON_LEAVES = st.one_of(st.none(), st.booleans(), st.integers(-2 ** 70, 2 ** 70), st.sampled_from([10 ** 400, -1]),
                        st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20))
JSON_VALUES = st.recursive(JSON_LEAVES, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.text(max_size=8), inner, max_size=4), max_leaves=12)


def json_paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (keys and indices) to a value inside a parsed JSON document, the root's () first."""
    paths = [prefix]
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        paths += json_paths(child, prefix + (key,))
    return paths


def json_replaced(document: Any, path: tuple, new: Any) -> bytes:
    """The JSON bytes of `document` with the value at `path` replaced by `new` (NaN and infinity as Python's json
    writes them: NaN, Infinity)."""
    if not path:
        return json.dumps(new).encode()
    copy = json.loads(json.dumps(document))
    target = copy
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = new
    return json.dumps(copy).encode()


def deeply_nested(depth: int) -> bytes:
    """A JSON array nested `depth` deep."""
    return b"[" * depth + b"]" * depth


def mutations(seeds: dict[str, bytes], fields: dict[str, dict[str, Field]]) -> st.SearchStrategy[Case]:
    """Mutated seeds: one file of `seeds` ({file: bytes}) truncated, with bytes flipped, a header field of `fields`
    ({file: {name: Field}}) lying, a chunk spliced in, replaced by random bytes, or (a JSON file) a value replaced."""
    files = sorted(seeds)

    def mutate(file: str, draw: Callable) -> Case:
        data = seeds[file]
        kinds = ["truncate", "flip", "splice", "random"] + ["field"] * bool(fields.get(file))
        kinds += ["json"] * file.endswith(".json")
        kind = draw(st.sampled_from(kinds))
        if kind == "truncate":
            at = draw(st.integers(0, max(len(data) - 1, 0)))
            return Case(f"{file} truncated to {at} bytes", file, truncated(data, at))
        if kind == "flip":
            edits = draw(st.lists(st.tuples(st.integers(0, 2 ** 20), st.integers(0, 255)), min_size=1, max_size=8))
            return Case(f"{file} with bytes {edits} set", file, flipped(data, edits))
        if kind == "splice":
            at, chunk = draw(st.integers(0, len(data))), draw(st.binary(min_size=1, max_size=256))
            return Case(f"{file} with {len(chunk)} bytes spliced in at {at}", file, spliced(data, at, chunk))
        if kind == "field":
            name = draw(st.sampled_from(sorted(fields[file])))
            value = draw(st.sampled_from(HUGE) | st.integers(0, 2 ** 64 - 1))
            return Case(f"{file} {name} = {value}", file, fields[file][name](data, value))
        if kind == "json":
            document = json.loads(data)
            path = draw(st.sampled_from(json_paths(document)))
            new = draw(JSON_VALUES)
            return Case(f"{file} value at {list(path)} = {str(new)[:60]}", file, json_replaced(document, path, new))
        content = draw(st.binary(max_size=2048))
        return Case(f"{file}: {len(content)} random bytes", file, content)

    return st.composite(lambda draw: mutate(draw(st.sampled_from(files)), draw))()


def packed(data: bytes, offset: int, fmt: str, *values: Any) -> bytes:
    """`data` with `values` written at `offset` in struct format `fmt` (little endian)."""
    out = bytearray(data)
    struct.pack_into("<" + fmt, out, offset, *values)
    return bytes(out)
