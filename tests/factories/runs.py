"""Running stages directly: a stage's Context, the short chains of stages the stress cases use, and the real
plush dog's chain with the defaults (../shared/real)."""
from __future__ import annotations

import json
from pathlib import Path

from stages.app.pipeline import STAGES, Graph, build_graph
from stages.bg_depth import run as bg_depth
from stages.compose import run as compose
from stages.contract.fan_in import fan_in
from stages.engine.cache_entry import Outcome
from stages.engine.cache_keys import derive_seed
from stages.engine.context import Context
from stages.engine.graph import Node
from stages.engine.scheduler import Engine
from stages.planes import run as planes
from tests.factories.configs import REAL, compose_cfg
from tests.factories.splats import write_blob_object

DOG = "plush_dog"  # the real capture's object, its item in real_config's graph
BLOB_HEIGHT_M = 0.3  # metres: make_blob's real height in the compose runs


def stage_ctx(stage: str, inputs: dict, out: Path, params: dict | None = None, item: str = "stress") -> Context:
    """A Context for calling a stage's `run` directly, writing into a fresh `out` folder."""
    out.mkdir(parents=True, exist_ok=True)
    return Context(stage=stage, item=item, params=dict(params or {}), inputs=inputs, out=out, seed=0)


def depth_planes_compose(root: Path, photo: dict[str, Path], num_images: int) -> dict:
    """bg_depth (provider auto, model none) -> planes -> compose on one photo; the three stages' metrics."""
    depth_out, planes_out, compose_out = root / "bg_depth", root / "planes", root / "compose"
    depth_metrics = bg_depth.run(stage_ctx("bg_depth", photo, depth_out, {"provider": "auto", "model": "none"}))
    planes_metrics = planes.run(stage_ctx("planes", {"depth": depth_out, "image": photo["image"]}, planes_out))
    compose_inputs = {**fan_in({"blob": {"object": write_blob_object(root / "extract")}}, compose.INPUTS.object_kinds),
                      **fan_in({"bg": {"background": photo["image"], "planes": planes_out, "depth": depth_out}},
                               compose.INPUTS.photo_kinds)}
    compose_params = {"objects": [{"name": "blob", "height_m": BLOB_HEIGHT_M}], "num_images": num_images,
                      "preview_count": 2}
    compose_metrics = compose.run(stage_ctx("compose", compose_inputs, compose_out, compose_params))
    return {"bg_depth": depth_metrics, "planes": planes_metrics, "compose": compose_metrics,
            "planes_json": json.loads((planes_out / "planes.json").read_text()),
            "stats_json": json.loads((compose_out / "stats.json").read_text())}


def frames_sfm_run(cache: Path, videos: dict[str, Path], frames_params: dict, sfm_params: dict) -> list[Outcome]:
    """frames -> sfm nodes per object (the pipeline's stages) in one Engine run (not strict)."""
    targets = []
    for name, video in videos.items():
        frames_node = Node(STAGES["frames"], name, frames_params, {"video": video})
        targets.append(Node(STAGES["sfm"], name, sfm_params, {"frames": frames_node}))
    return Engine(cache).run(targets)


def real_config(until: str):
    """The real plush dog's run config: the defaults with folder data, object plush_dog (0.25 m, the 84 photos
    of ../shared/real/plush_dog/images) and the real RGB-D photos of ../shared/real/rgbd as backgrounds."""
    return compose_cfg(["data=folder", f"data.objects=[{{name: {DOG}, height_m: 0.25, "
                                       f"video: '{REAL / DOG / 'images'}'}}]",
                        f"data.backgrounds='{REAL / 'rgbd'}'", "data.test_sets=[]", f"run.until={until}"])


def real_seed(stage: str) -> int:
    """The seed the engine gives the real dog's node of `stage` in a dag.py run of real_config."""
    return derive_seed(int(real_config(stage).run.seed), stage, DOG)


def run_real_chain(cache: Path, until: str) -> tuple[Engine, Graph, list[Outcome]]:
    """Run the real plush dog's graph (what `dag.py` builds from real_config) up to stage `until` with the
    engine and cache folder `cache`; cached nodes are not rerun."""
    cfg = real_config(until)
    engine = Engine(cache, global_seed=int(cfg.run.seed))
    graph = build_graph(cfg, REAL)
    return engine, graph, engine.run(graph.targets(until))


def object_dirs(engine: Engine, graph: Graph) -> dict[str, Path]:
    """Output folders of the first object's frames, sfm, splat_train and extract nodes."""
    return {stage: engine.output_dir(graph.nodes[stage][0]) for stage in ("frames", "sfm", "splat_train", "extract")}
