"""The one spelling of a benchmark's setting changes: `--set KEY=VALUE [KEY=VALUE ...]` (repeatable), each value
read as JSON where it parses (numbers, lists, true, null), else kept as text (`backend=gsplat`).

    add_set_option(parser, "splat_train's settings")
    changes = changed_settings(args.set, asdict(SplatTrainConfig()))  # {key: value}, checked against the defaults

(captures takes Hydra's own `stage.key=value` overrides instead: it composes a whole run's config; dog_trainings
spells its keys the same way, extract.KEY.)
"""
from __future__ import annotations

import argparse
import json


def setting(text: str) -> tuple[str, object]:
    """`KEY=VALUE` as (key, value), the value read as JSON where it parses, else kept as text; an
    argparse.ArgumentTypeError without a key or an '='."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"wants KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def add_set_option(parser: argparse.ArgumentParser, what: str, flag: str = "--set") -> None:
    """Add `flag` KEY=VALUE ... (repeatable) to `parser`, parsed by `setting` into a list of (key, value) pairs;
    `what` names the settings it changes, for the help."""
    parser.add_argument(flag, type=setting, nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                        help=f"change {what} (each value read as JSON where it parses)")


def changed_settings(pairs: list[tuple[str, object]], defaults: dict, flag: str = "--set") -> dict[str, object]:
    """The (key, value) pairs as a dict, checked against `defaults` (each setting's default value): SystemExit
    naming a key that is not a setting, or a value of another kind than its default's (an int for a float is
    fine; any value where the default is None)."""
    for key, value in pairs:
        if key not in defaults:
            raise SystemExit(f"{flag} {key}=...: {key!r} is not a setting here ({', '.join(defaults)})")
        if not _same_kind(value, defaults[key]):
            raise SystemExit(f"{flag} {key}={value}: {value!r} is not a {type(defaults[key]).__name__} like its "
                             f"default {defaults[key]!r}")
    return dict(pairs)


def _same_kind(value: object, default: object) -> bool:
    """Whether `value` may stand where `default` does (changed_settings)."""
    if default is None:
        return True
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(value, bool) and isinstance(default, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float))
    if isinstance(default, (list, tuple)):
        return isinstance(value, list)
    return isinstance(value, type(default))
