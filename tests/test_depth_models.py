"""The monocular depth model of bg_depth (stages/lib/depth/models.py, stages/lib/depth/transformers.py): which model a
photo gets, the pinned checkpoint loaded from the Hugging Face cache offline, the one error when it is neither
cached nor fetchable, and the default run that never loads it. The models are tiny random ones of the published
architecture (tests/factories/depth_models.py); nothing is downloaded (tests/conftest.py: offline_hub)."""
from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from stages.app.pipeline import build_graph
from stages.app.preflight import check_inputs
from stages.app.summary import run_report, summarise
from stages.bg_depth import run as bg_depth
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.engine.scheduler import Engine
from stages.lib.depth import models as depth_models
from stages.lib.depth import transformers as depth_transformers
from stages.lib.depth.models import DEFAULT_MODEL, DEPTH_MODELS, HubModel
from stages.lib.imageio import load_photo
from tests.factories.configs import ROOT, compose_cfg
from tests.factories.depth_models import save_model, tiny_config
from tests.factories.media import noise_video, write_image
from tests.factories.rooms import room_depth

DEFAULT = DEPTH_MODELS[DEFAULT_MODEL]


def photo(path, seed: int = 0, size: tuple[int, int] = (48, 64)):
    """A random RGB photo of `size` (height, width) written at `path`."""
    pixels = np.random.default_rng(seed).integers(0, 255, (*size, 3), dtype=np.uint8)
    return write_image(path, pixels)


def run_depth(tmp_path, name: str, params: dict, inputs: dict, device: str = "cpu") -> tuple[dict, dict, np.ndarray]:
    """bg_depth.run into tmp_path/name: (metrics, depth.json, depth.npy)."""
    out = tmp_path / name
    out.mkdir()
    metrics = bg_depth.run(Context("bg_depth", name, params, inputs, out, device=device))
    return metrics, json.loads((out / "depth.json").read_text()), np.load(out / "depth.npy")


def folder_data(tmp_path, with_sidecar: tuple[str, ...], without: tuple[str, ...], *overrides: str):
    """A data=folder config whose photos are `with_sidecar` (a metric depth sidecar beside each) and `without`."""
    photos = tmp_path / "photos"
    photos.mkdir(exist_ok=True)
    depth, _, _ = room_depth(64, 48)
    for k, name in enumerate(with_sidecar + without):
        photo(photos / f"{name}.png", k)
        if name in with_sidecar:
            write_image(photos / f"{name}.depth.png", np.rint(depth * 1000).astype(np.uint16))
    (tmp_path / "videos").mkdir(exist_ok=True)
    noise_video(tmp_path / "videos" / "mug.mp4", 2, 64, 48)
    return compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/mug.mp4}]",
                        "data.backgrounds=photos", "data.test_sets=[]", *overrides])


def test_every_published_model_is_pinned_to_a_commit():
    for model in DEPTH_MODELS.values():
        assert depth_models.check_pinned(model) is model and len(model.revision) == 40
    with pytest.raises(ValueError, match="revision 'main' is not a commit sha"):
        depth_models.check_pinned(HubModel("depth-anything/x", "main", "disparity", "Apache-2.0"))


def test_the_model_setting_names_an_alias_a_file_a_folder_or_none(tmp_path, offline_hub):
    source = depth_models.resolve_model("relative-small", tmp_path)
    assert source.kind == "hub" and source.hub.output == "disparity"
    assert source.path == (offline_hub / "models--depth-anything--Depth-Anything-V2-Small-hf" / "snapshots"
                           / source.hub.revision / "config.json")
    assert depth_models.resolve_model("models/da.onnx", tmp_path).path == tmp_path / "models" / "da.onnx"
    assert depth_models.resolve_model("./my_model", tmp_path).kind == "folder"
    assert depth_models.resolve_model("none", tmp_path).kind == "none"
    with pytest.raises(ValueError, match="'metric-indor-small' is neither a known model \\(metric-indoor-small"):
        depth_models.resolve_model("metric-indor-small", tmp_path)


def test_the_default_model_runs_from_the_hugging_face_cache_offline(tmp_path, cached_depth_model, one_thread):
    """A photo without sidecar, default settings: the pinned snapshot in the cache (no network), named in
    depth.json and in the metrics; the depth is the model's own metres."""
    image = photo(tmp_path / "desk.png")
    metrics, record, depth = run_depth(tmp_path, "desk", {}, {"image": image})
    assert record["provider"] == "model" and record["metric"] is True and record["recovery"] is None
    assert record["model"] == {"name": DEFAULT_MODEL, "kind": "hub", "repo": DEFAULT.repo, "revision": DEFAULT.revision,
                               "licence": "Apache-2.0", "output": "metric_depth"}
    assert metrics["model"] == f"{DEFAULT_MODEL} ({DEFAULT.repo}@{DEFAULT.revision})"
    snapshot = cached_depth_model / DEFAULT.folder_name() / "snapshots" / DEFAULT.revision
    model = depth_transformers.load_depth_model(str(snapshot), "cpu")
    own = depth_transformers.run_depth_model(model, load_photo(image), 518)
    np.testing.assert_allclose(depth, own, rtol=1e-5)
    assert 0 < depth.min() and depth.max() <= 20.0  # the metric head: sigmoid x max_depth 20 m


def test_the_dag_gives_the_model_only_to_photos_without_sidecar(tmp_path, cached_depth_model, one_thread):
    cfg = folder_data(tmp_path, ("kitchen",), ("hall", "porch"))
    graph = build_graph(cfg, tmp_path)
    nodes = {node.item: node for node in graph.nodes["bg_depth"]}
    snapshot = cached_depth_model / DEFAULT.folder_name() / "snapshots" / DEFAULT.revision
    assert nodes["hall"].inputs["model"] == snapshot / "config.json" and nodes["hall"].params["model"] == DEFAULT_MODEL
    assert "model" not in nodes["kitchen"].inputs and nodes["kitchen"].params["model"] == "none"
    assert check_inputs(graph, ["mug"]) == {}
    engine = Engine(tmp_path / "cache")
    keys = {item: engine.key(node) for item, node in nodes.items()}
    own = save_model(tmp_path / "my_model", tiny_config("relative"))
    other_cfg = folder_data(tmp_path, ("kitchen",), ("hall", "porch"), f"bg_depth.model={own}")
    other = {node.item: node for node in build_graph(other_cfg, tmp_path).nodes["bg_depth"]}
    assert other["hall"].inputs["model"] == own and other["hall"].params["model"] == "local"
    assert Engine(tmp_path / "cache").key(other["hall"]) != keys["hall"]  # another model: the photo reruns
    assert Engine(tmp_path / "cache").key(other["kitchen"]) == keys["kitchen"]  # its sidecar: it stays cached
    _, record, depth = run_depth(tmp_path, "hall", nodes["hall"].params, dict(nodes["hall"].inputs))
    _, direct, same = run_depth(tmp_path, "direct", {}, {"image": nodes["hall"].inputs["image"]})
    assert record == direct
    np.testing.assert_array_equal(depth, same)


def test_offline_without_the_model_is_one_error_before_any_stage(tmp_path):
    """Three photos need the model, the cache is empty and the Hub offline: one problem, naming the model and
    how to place it by hand; the three bg_depth nodes are bad inputs, the photo with a sidecar is not."""
    cfg = folder_data(tmp_path, ("kitchen",), ("hall", "porch", "attic"))
    graph = build_graph(cfg, tmp_path)
    started = time.perf_counter()
    problems = check_inputs(graph, ["mug"])
    assert time.perf_counter() - started < 5.0
    assert len(problems) == 1
    message = next(iter(problems.values()))
    for part in (f"depth model {DEFAULT_MODEL} ({DEFAULT.repo} at revision {DEFAULT.revision})",
                 "HF_HUB_OFFLINE is set", f"hf download {DEFAULT.repo} config.json model.safetensors --revision "
                 f"{DEFAULT.revision}", "bg_depth.model=/path/to/DIR", "bg_depth.model=none"):
        assert part in message, part
    records = Engine(tmp_path / "cache").plan(graph.targets("bg_depth"), problems)
    assert {r.item: r.status for r in records} == {"kitchen": "would-run", "hall": "bad-input", "porch": "bad-input",
                                                  "attic": "bad-input"}


def test_an_unreachable_hub_is_told_within_the_probe_timeout(monkeypatch):
    """Not offline by setting, but the Hub does not answer (a closed local port stands for it): the probe's one
    request fails at once and the error says so; nothing is fetched."""
    import huggingface_hub.constants as constants

    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(constants, "ENDPOINT", f"http://127.0.0.1:{port}")
    started = time.perf_counter()
    with pytest.raises(StageError, match=f"cannot be fetched: http://127.0.0.1:{port} cannot be reached"):
        depth_models.ensure_hub_model(DEFAULT_MODEL, DEFAULT, timeout_s=2.0)
    assert time.perf_counter() - started < depth_models.PROBE_TIMEOUT_S


def test_a_relative_model_folder_gives_metres_by_recovery(tmp_path, one_thread):
    folder = save_model(tmp_path / "my_relative_model", tiny_config("relative"))
    image = photo(tmp_path / "room.png")
    params = {"provider": "model", "model": str(folder), "model_input_size": 56}
    metrics, record, depth = run_depth(tmp_path, "room", params, {"image": image})
    assert record["model"] == {"name": str(folder), "kind": "folder", "path": str(folder), "output": "disparity"}
    assert record["metric"] is True and set(record["recovery"]) == {"shift", "shift_from", "scale_m", "scale_from",
                                                                     "score_deg", "patches"}
    assert metrics["recovery"] == record["recovery"] and (depth > 0).mean() > 0.9


def test_a_model_folder_without_its_weights_is_named(tmp_path):
    folder = save_model(tmp_path / "half", tiny_config("metric"))
    (folder / "model.safetensors").unlink()
    with pytest.raises(StageError, match="depth model folder .*half: model.safetensors missing"):
        depth_models.check_model_input(folder, {"model": "local"})
    (folder / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(StageError, match="model_type 'bert', expected 'depth_anything'"):
        depth_transformers.model_output_kind(folder)


def test_the_summary_says_where_each_photo_got_its_depth(tmp_path):
    from stages.engine.cache_entry import METRICS, Outcome

    records = []
    for item, metrics in (("kitchen", {"provider": "sidecar", "sidecar_format": "png_mm"}),
                          ("hall", {"provider": "model", "model": "metric-indoor-small (repo@sha)"}),
                          ("porch", {"provider": "model", "model": "metric-indoor-small (repo@sha)"})):
        (tmp_path / item).mkdir()
        (tmp_path / item / METRICS).write_text(json.dumps(metrics))
        records.append(Outcome("bg_depth", item, "k", "ran", path=str(tmp_path / item)))
    summary = summarise(records, compose_cfg([]), {}, [])
    assert summary["depth_sources"] == {"sidecar png_mm": 1, "model metric-indoor-small (repo@sha)": 2}
    assert ("photo depth: 1 from sidecar png_mm, 2 from model metric-indoor-small (repo@sha)"
            in run_report(summary, records, tmp_path / "summary.json").splitlines())


def test_the_default_run_neither_imports_transformers_nor_the_hub_client(tmp_path):
    """The embedded sample's photos all have sidecars: building its graph, checking its inputs and running bg_depth
    on a photo with a sidecar load neither transformers nor huggingface_hub."""
    depth, _, _ = room_depth(64, 48)
    photo(tmp_path / "bg.png")
    write_image(tmp_path / "bg.depth.png", np.rint(depth * 1000).astype(np.uint16))
    script = f"""
import sys
from pathlib import Path
from tests.factories.configs import ROOT, compose_cfg
from stages.app.pipeline import build_graph
from stages.app.preflight import check_inputs
from stages.engine.context import Context
graph = build_graph(compose_cfg([]), ROOT)
assert check_inputs(graph, []) == {{}}
node = graph.nodes["bg_depth"][0]
assert node.params["model"] == "none" and "model" not in node.inputs, node.params
from stages.bg_depth import run as bg_depth
out = Path({str(tmp_path)!r}) / "out"
out.mkdir()
bg_depth.run(Context("bg_depth", "bg", node.params, {{"image": Path({str(tmp_path / 'bg.png')!r})}}, out))
print(sorted(m for m in ("transformers", "huggingface_hub") if m in sys.modules))
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_model_runs_on_the_gpu(tmp_path, cached_depth_model):
    image = photo(tmp_path / "desk.png")
    _, _, on_cpu = run_depth(tmp_path, "cpu", {}, {"image": image})
    _, _, on_gpu = run_depth(tmp_path, "gpu", {}, {"image": image}, device="cuda")
    snapshot = cached_depth_model / DEFAULT.folder_name() / "snapshots" / DEFAULT.revision
    assert next(depth_transformers.load_depth_model(str(snapshot), "cuda").parameters()).is_cuda
    np.testing.assert_allclose(on_gpu, on_cpu, rtol=1e-3, atol=1e-3)
