"""A node's settings checked against the config class its stage declares (`Stage.config`, the spec's
`<Name>Config`), once, at start: the check OmegaConf makes when Hydra composes a config (keys, types, choices), for
settings given directly (tests, benchmarks, other tools) too, then the class's own value checks. The stage receives
the typed settings (`Context.typed`); keys keep hashing the plain values."""
from __future__ import annotations

from typing import Any

import numpy as np
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from stages.contract.errors import StageError


def python_values(value: Any) -> Any:
    """`value` with numpy scalars (also inside dicts, lists and tuples) as the Python numbers OmegaConf takes."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {key: python_values(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [python_values(item) for item in value]
    return value


def check_params(config: type, stage: str, params: dict) -> None:
    """StageError when `params` do not fit `config`, the dataclass of `stage`'s settings (a key it does not have, a
    wrong type, a value outside a `choices` Enum), naming the key."""
    try:
        OmegaConf.merge(OmegaConf.structured(config), python_values(params))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", "") or "?"
        raise StageError(f"{stage} settings: {str(error).splitlines()[0]} (full key: {stage}.{key})") from error


def typed_settings(config: type, stage: str, params: dict) -> Any:
    """`params` as an instance of `config`, checked once (check_params, then the class's own value checks in
    __post_init__), built from the plain values as `config(**params)`; StageError naming the setting."""
    check_params(config, stage, params)
    try:
        return config(**params)
    except ValueError as error:
        raise StageError(str(error)) from error
