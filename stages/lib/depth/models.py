"""Which monocular depth model bg_depth runs on a photo without a depth sidecar, and where its files are.

`bg_depth.model` is one of:
- an alias of DEPTH_MODELS: a published Depth Anything V2 checkpoint on the Hugging Face Hub, pinned to a commit
  (a 40-hex sha; an unpinned revision is refused), fetched once into the standard Hugging Face cache
  (``$HF_HUB_CACHE``, by default ``$HF_HOME/hub`` = ``~/.cache/huggingface/hub``) when a run first needs it;
- a folder in `save_pretrained` layout (config.json + model.safetensors of a ``DepthAnythingForDepthEstimation``);
- an ``.onnx`` file (stages/lib/depth/onnx.py);
- ``none``: no model; a photo without sidecar then has no depth (and no placement plane).

The default, ``metric-indoor-small`` = depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf, and why:
- metric: it predicts metres (Depth Anything V2 Small fine-tuned on the synthetic indoor Hypersim set, max 20 m), so
  compose stands objects at their real size without guessing a scale; the paper's reference code also uses a metric
  indoor Depth Anything (V1). Relative models need the scale from priors (stages/lib/depth/recovery.py), off by a
  median factor of 1.2 on the embedded sample (benchmarks/mono_depth.py).
- licence: Apache-2.0 as far as the cards say: the Depth-Anything-V2 README puts the Small model under Apache-2.0
  (Base/Large/Giant under CC-BY-NC-4.0: not a default); the cards of depth-anything/Depth-Anything-V2-Small(-hf)
  and of the original metric checkpoints (Metric-Hypersim-Base/-Large, Metric-VKITTI-Small) say apache-2.0. The
  -hf metric conversions' own cards carry no licence tag (to confirm before a commercial use).
- size: 24.8 M parameters, a 99.2 MB model.safetensors (fp32).
- speed: 2.3 s per 640x480 photo (fed at 518x686) on one CPU thread of the 2-core machine, measured with a
  randomly initialised model of the same architecture (python -m benchmarks.mono_depth --speed; BENCHMARKS.md).
The others: ``metric-outdoor-small`` (Virtual KITTI 2, max 80 m) for outdoor photos and ``relative-small``
(Depth-Anything-V2-Small-hf, affine-invariant disparity; scale and shift recovered per photo).

Nothing here imports huggingface_hub or transformers at module level: the default run on the embedded sample,
whose photos all have sidecars, never loads them.
"""
from __future__ import annotations

import logging
import re
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from stages.contract.errors import StageError

log = logging.getLogger(__name__)

HUB_FILES = ("config.json", "model.safetensors")  # what a hub snapshot must hold (preprocessing is ours)
PROBE_TIMEOUT_S = 5.0  # one request to the Hub before fetching: an offline machine answers within this
PINNED = re.compile(r"^[0-9a-f]{40}$")
NO_MODEL = ("none", "")


@dataclass(frozen=True)
class HubModel:
    """A published checkpoint: repository, pinned commit, what it outputs and its licence."""

    repo: str
    revision: str  # a commit sha (40 hex digits)
    output: str  # "metric_depth" (metres) | "disparity" (affine-invariant, relative)
    licence: str

    def folder_name(self) -> str:
        """The repository's folder in the Hugging Face cache."""
        return "models--" + self.repo.replace("/", "--")


DEPTH_MODELS = {
    "metric-indoor-small": HubModel("depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf",
                                    "4d5187ef4957085a714f15b6ae43230a8b813c03", "metric_depth", "Apache-2.0"),
    "metric-outdoor-small": HubModel("depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf",
                                     "fd2c22027eaf20374204f14099b8341e1925ad39", "metric_depth", "Apache-2.0"),
    "relative-small": HubModel("depth-anything/Depth-Anything-V2-Small-hf",
                               "870a35c76c2bc1d82fbde922d95015496cb7dd6c", "disparity", "Apache-2.0"),
}
DEFAULT_MODEL = "metric-indoor-small"


@dataclass(frozen=True)
class ModelSource:
    """What `bg_depth.model` names. kind: "hub" (an alias) | "folder" | "onnx" | "none"; path: the hub snapshot's
    config.json (which exists once the model is in the cache), the folder or the .onnx file; None for "none"."""

    kind: str
    name: str
    path: Path | None = None
    hub: HubModel | None = None

    def describe(self) -> dict:
        """What depth.json and the run summary say about the model: name, kind, and repo + revision or path."""
        if self.hub is not None:
            return {"name": self.name, "kind": self.kind, "repo": self.hub.repo, "revision": self.hub.revision,
                    "licence": self.hub.licence}
        return {"name": self.name, "kind": self.kind, "path": str(self.path) if self.path else None}


def check_pinned(model: HubModel) -> HubModel:
    """`model`, or ValueError when its revision is not a commit sha (a branch would change under the cache)."""
    if not PINNED.match(model.revision):
        raise ValueError(f"depth model {model.repo}: revision {model.revision!r} is not a commit sha (40 hex "
                         "digits); pin it to the commit whose files were checked")
    return model


def hub_cache() -> Path:
    """The Hugging Face hub cache folder in effect ($HF_HUB_CACHE, $HF_HOME/hub, ~/.cache/huggingface/hub)."""
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def snapshot_folder(model: HubModel) -> Path:
    """Where the pinned snapshot of `model` lies in the Hugging Face cache (whether or not it is there yet)."""
    return hub_cache() / model.folder_name() / "snapshots" / check_pinned(model).revision


def resolve_model(spec: str, base: Path) -> ModelSource:
    """The model `bg_depth.model` names (module doc); paths relative to `base`. ValueError for a name that is
    neither an alias nor a path."""
    spec = str(spec).strip()
    if spec in NO_MODEL:
        return ModelSource("none", "none")
    if spec in DEPTH_MODELS:
        hub = check_pinned(DEPTH_MODELS[spec])
        return ModelSource("hub", spec, snapshot_folder(hub) / HUB_FILES[0], hub)
    path = Path(spec).expanduser()
    path = path if path.is_absolute() else base / path
    if path.suffix.lower() == ".onnx":
        return ModelSource("onnx", spec, path)
    if path.is_dir() or "/" in spec or spec.startswith((".", "~")):
        return ModelSource("folder", spec, path)
    raise ValueError(f"bg_depth.model={spec!r} is neither a known model ({', '.join(DEPTH_MODELS)}), nor an .onnx "
                     "file, nor a folder of a saved DepthAnything model; 'none' runs without a model")


def node_model(params: dict, has_sidecar: bool, base: Path) -> tuple[dict, dict[str, Path]]:
    """One photo's bg_depth node: its params and the model input it reads.

    A photo the model does not serve (provider "sidecar", or "auto" with a sidecar) gets model "none", so that
    changing the model reruns only the photos that use it. An alias stays in the params (its pinned revision is in
    this module's code, which is in the stage's cache key) and its snapshot's config.json is the input; a folder or
    an .onnx file is the input (its content enters the key, not its path) and the params say "local".
    """
    serves = params["provider"] == "model" or (params["provider"] == "auto" and not has_sidecar)
    source = resolve_model(params["model"], base) if serves else ModelSource("none", "none")
    if source.kind == "none":
        return {**params, "model": "none"}, {}
    return {**params, "model": source.name if source.kind == "hub" else "local"}, {"model": source.path}


def cached_snapshot(model: HubModel) -> Path | None:
    """The snapshot folder of `model` when the Hugging Face cache holds all of HUB_FILES, else None (no network)."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    try:
        folder = Path(snapshot_download(model.repo, revision=check_pinned(model).revision,
                                        allow_patterns=list(HUB_FILES), local_files_only=True))
    except (LocalEntryNotFoundError, FileNotFoundError):
        return None
    return folder if all((folder / name).is_file() for name in HUB_FILES) else None


def probe_hub(model: HubModel, timeout_s: float = PROBE_TIMEOUT_S) -> str | None:
    """None when the Hub answers for `model`'s revision within `timeout_s` (one request, no retries); else why not."""
    from huggingface_hub import constants

    url = f"{constants.ENDPOINT}/api/models/{model.repo}/revision/{model.revision}"
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout_s):
            return None
    except urllib.error.HTTPError as error:
        return f"{url} answered HTTP {error.code}"
    except (urllib.error.URLError, OSError) as error:  # no route, no DNS, timeout
        return f"{constants.ENDPOINT} cannot be reached ({getattr(error, 'reason', error)})"


def unavailable_message(name: str, model: HubModel, reason: str) -> str:
    """The one error for a hub model that is neither cached nor fetchable: which model, why, how to place it by hand."""
    cache = hub_cache()
    return (f"depth model {name} ({model.repo} at revision {model.revision}), which the photos without a depth "
            f"sidecar need, is not in the Hugging Face cache {cache} and cannot be fetched: {reason}. To place it by "
            f"hand, on a machine with network run `hf download {model.repo} {' '.join(HUB_FILES)} --revision "
            f"{model.revision}` (huggingface_hub's CLI; `huggingface-cli download` in older versions) and copy its "
            f"folder ~/.cache/huggingface/hub/{model.folder_name()} to {cache / model.folder_name()}; or add "
            f"`--local-dir DIR` to that command, copy DIR here and set bg_depth.model=/path/to/DIR; or give those "
            "photos depth sidecars; or set bg_depth.model=none to compose them without placement planes")


def ensure_hub_model(name: str, model: HubModel, timeout_s: float = PROBE_TIMEOUT_S) -> Path:
    """The snapshot folder of a hub model, fetched into the Hugging Face cache once when it is missing.

    Offline ($HF_HUB_OFFLINE, or the Hub not answering within `timeout_s`) without a cached copy: StageError with
    unavailable_message. Never waits longer than the probe's timeout when there is no network.
    """
    folder = cached_snapshot(model)
    if folder is not None:
        return folder
    from huggingface_hub import constants, snapshot_download

    reason = "HF_HUB_OFFLINE is set" if constants.HF_HUB_OFFLINE else probe_hub(model, timeout_s)
    if reason is not None:
        raise StageError(unavailable_message(name, model, reason))
    log.warning("fetching depth model %s (%s at %s, about 100 MB) into %s, once", name, model.repo,
                model.revision[:7], hub_cache())
    try:
        snapshot_download(model.repo, revision=model.revision, allow_patterns=list(HUB_FILES))
    except Exception as error:  # huggingface_hub raises many types (HTTP, disk, interrupted download)
        raise StageError(unavailable_message(name, model, f"the download failed ({error})")) from error
    folder = cached_snapshot(model)
    if folder is None:
        raise StageError(unavailable_message(name, model, f"the download did not give {', '.join(HUB_FILES)}"))
    return folder


def check_model_input(path: Path, params: dict) -> None:
    """Preflight of a bg_depth node's `model` input: a hub alias is in the cache (fetched now when it is not and
    the Hub answers; else the one error of unavailable_message), a folder holds a DepthAnything config.json and
    model.safetensors, an .onnx file exists. StageError naming the model otherwise."""
    name = params.get("model", "")
    if name in DEPTH_MODELS:
        ensure_hub_model(name, DEPTH_MODELS[name])
        return
    if not path.exists():
        raise StageError(f"depth model {path}: not found (bg_depth.model names a folder of a saved DepthAnything "
                         f"model or an .onnx file, or one of {', '.join(DEPTH_MODELS)})")
    if path.is_dir():
        missing = [name for name in HUB_FILES if not (path / name).is_file()]
        if missing:
            raise StageError(f"depth model folder {path}: {', '.join(missing)} missing (save_pretrained layout of a "
                             "DepthAnythingForDepthEstimation expected)")
