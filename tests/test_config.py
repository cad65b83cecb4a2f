"""Hydra config: the schema rejects typos, every experiment composes, and every sweep job plans."""
from __future__ import annotations

import itertools
import re

import pytest
from omegaconf import OmegaConf

from stages.app.pipeline import GENERATORS, ORDER, build_graph
from stages.contract.fan_in import OBJECT_KINDS, PHOTO_KINDS, fanned
from stages.engine.scheduler import Engine
from stages.splat_train.run import SplatTrainConfig
from tests.factories.configs import CONF, REAL, ROOT, compose_cfg, composition_error
from tests.factories.media import noise_video

EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def test_default_config_builds_the_full_graph(tmp_path):
    cfg = compose_cfg([])
    graph = build_graph(cfg, ROOT)
    counts = {stage: len(nodes) for stage, nodes in graph.nodes.items()}
    n_obj, n_bg = len(cfg.data.objects), cfg.sample.num_backgrounds
    assert counts == {"sample": 1, "frames": n_obj, "sfm": n_obj, "splat_train": n_obj, "extract": n_obj,
                      "bg_depth": n_bg, "planes": n_bg, "compose": cfg.compose.num_images // cfg.compose.shard_size,
                      "dataset": 1, "train_maskrcnn": 1, "eval": 2}
    records = Engine(tmp_path / "cache").plan(graph.targets(None))
    assert {r.status for r in records} == {"would-run"} and len(records) == sum(counts.values())


@pytest.mark.parametrize("override, key", [("compose.varaint=full", "compose.varaint"),
                                           ("train_maskrcnn.iteratons=3", "train_maskrcnn.iteratons"),
                                           ("sfm.fist_octave=1", "sfm.fist_octave")])
def test_mistyped_key_fails_naming_it(override, key):
    with pytest.raises(Exception, match=key.replace(".", r"\.")):
        compose_cfg([override])


def test_wrong_value_type_fails():
    with pytest.raises(Exception, match="splat"):
        compose_cfg(["splat_train.iterations=many"])


def test_variants_share_everything_up_to_the_dataset(tmp_path):
    engine = Engine(tmp_path / "cache")
    keys = {}
    for variant in ("full", "no_aug", "cut_and_paste"):
        graph = build_graph(compose_cfg([f"variant={variant}"]), ROOT)
        keys[variant] = {(n.stage.name, n.item): engine.key(n) for nodes in graph.nodes.values() for n in nodes}
        engine._keys.clear()
    shared = [k for k in keys["full"] if k[0] in ("sample", "frames", "sfm", "splat_train", "extract", "planes")]
    assert shared and all(keys["full"][k] == keys["no_aug"][k] == keys["cut_and_paste"][k] for k in shared)
    assert keys["full"][("compose", "full#0")] != keys["no_aug"][("compose", "no_aug#0")]
    assert ("cut_and_paste", "cut_and_paste#0") in keys["cut_and_paste"]


def test_effect_variants_take_the_seeds_of_full(tmp_path):
    """shadow, relight and effects are paired with full (variant.seed_as): the same seeds for compose, the detector
    and eval, so their datasets hold the same placements; other variants draw their own."""
    engine = Engine(tmp_path / "cache", global_seed=3)
    seeds = {}
    for variant in ("full", "shadow", "effects", "no_aug"):
        graph = build_graph(compose_cfg([f"variant={variant}"]), ROOT)
        seeds[variant] = [engine.seed(n) for stage in ("compose", "dataset", "train_maskrcnn", "eval")
                          for n in graph.nodes[stage]]
    assert len(seeds["full"]) == 8 and len(set(seeds["full"])) == 5  # 4 compose shards with the dataset's seed,
    #                                                                   the dataset, train, eval of tests A and B
    assert seeds["shadow"] == seeds["effects"] == seeds["full"]
    assert not set(seeds["no_aug"]) & set(seeds["full"])


def sweep_jobs(experiment: str) -> list[list[str]]:
    """The override lists of every job of an experiment's sweep (one empty list for single runs)."""
    cfg = compose_cfg([f"+experiment={experiment}"], hydra_config=True)
    params = cfg.hydra.sweeper.params
    params = OmegaConf.to_container(params) if params is not None else {}
    axes = [[f"{key}={value}" for value in str(values).split(",")] for key, values in params.items()]
    return [list(job) for job in itertools.product(*axes)] if axes else [[]]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes_and_every_job_plans(experiment, tmp_path):
    if experiment == "real_dog" and not REAL.is_dir():
        pytest.skip(f"{REAL} not present (the real_dog experiment reads it)")
    if experiment == "mono_depth" and not (ROOT / "outputs" / "mono_depth").is_dir():
        pytest.skip("outputs/mono_depth not written (python -m benchmarks.mono_depth --write-backgrounds outputs/mono_depth)")
    jobs = sweep_jobs(experiment)
    assert jobs
    for job in jobs:
        cfg = compose_cfg([f"+experiment={experiment}", *job])
        graph = build_graph(cfg, ROOT)
        records = Engine(tmp_path / "cache").plan(graph.targets(cfg.run.until))
        assert records and records[-1].stage in ("eval", "extract", "planes", cfg.run.until)


def test_folder_data_requires_existing_paths(tmp_path):
    cfg = compose_cfg(["data=folder"])
    with pytest.raises(FileNotFoundError, match="background folder not found"):
        build_graph(cfg, tmp_path)


def test_folder_data_builds_per_photo_nodes_with_sidecars(tmp_path, cached_depth_model):
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "mug.mp4").write_bytes(b"not decoded at planning time")
    photos = tmp_path / "photos"
    photos.mkdir()
    for stem in ("kitchen", "office", "hall"):
        (photos / f"{stem}.jpg").write_bytes(stem.encode())
    (photos / "kitchen.depth.png").write_bytes(b"depth")
    (photos / "office.depth.tum.png").write_bytes(b"TUM depth")  # the file-name rule of stages/lib/depth/formats.py
    (tmp_path / "test" / "images").mkdir(parents=True)
    (tmp_path / "test" / "annotations.json").write_text("{}")
    cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/mug.mp4}]",
                       "data.backgrounds=photos", "data.test_sets=[{name: test, path: test}]"])
    graph = build_graph(cfg, tmp_path)
    depth_nodes = {n.item: n for n in graph.nodes["bg_depth"]}
    assert set(depth_nodes) == {"kitchen", "office", "hall"} and "sample" not in graph.nodes
    assert depth_nodes["kitchen"].inputs["depth"] == photos / "kitchen.depth.png"
    assert depth_nodes["office"].inputs["depth"] == photos / "office.depth.tum.png"
    assert "depth" not in depth_nodes["hall"].inputs
    records = Engine(tmp_path / "cache").plan(graph.targets(None))
    assert {r.status for r in records} == {"would-run"}


def test_folder_objects_on_the_sample_backgrounds_plus_own_photos(tmp_path):
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "mug.mp4").write_bytes(b"not decoded at planning time")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "desk_color.png").write_bytes(b"photo")
    (tmp_path / "photos" / "desk_depth.png").write_bytes(b"depth")
    cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/mug.mp4}]",
                       "data.backgrounds=photos", "data.sample_backgrounds=true", "data.test_sets=[]"])
    graph = build_graph(cfg, tmp_path)
    photos = sorted(n.item for n in graph.nodes["bg_depth"])
    assert photos == sorted(["desk_color"] + [f"bg{i:04d}" for i in range(cfg.sample.num_backgrounds)])
    default_sample = build_graph(compose_cfg([]), ROOT).nodes["sample"][0]
    engine = Engine(tmp_path / "cache")
    assert engine.key(graph.nodes["sample"][0]) == engine.key(default_sample)  # the default run's sample, cached
    assert [n.item for n in graph.nodes["frames"]] == ["mug"]
    # the sample's photos lacking a plane is information (some are views without a floor); the user's, a warning
    assert graph.nodes["compose"][0].params["expected_without_plane"] == [p for p in photos if p != "desk_color"]


def test_object_given_as_a_trained_model_skips_its_capture(tmp_path):
    """objects[].splat: only an extract node, reading the model file, with the object's up; Cut-and-Paste,
    which cuts objects out of their capture photos, stops at start naming the object."""
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "mug.mp4").write_bytes(b"not decoded at planning time")
    (tmp_path / "plant.splat").write_bytes(bytes(32))
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "kitchen.jpg").write_bytes(b"photo")
    objects = ("data.objects=[{name: mug, height_m: 0.1, video: videos/mug.mp4}, "
               "{name: plant, height_m: 0.3, splat: plant.splat, up: [0, -1, 0]}]")
    cfg = compose_cfg(["data=folder", objects, "data.backgrounds=photos", "data.test_sets=[]"])
    graph = build_graph(cfg, tmp_path)
    assert [n.item for n in graph.nodes["frames"]] == [n.item for n in graph.nodes["splat_train"]] == ["mug"]
    plant = next(n for n in graph.nodes["extract"] if n.item == "plant")
    assert plant.inputs == {"model": tmp_path / "plant.splat"} and plant.params["up_hint"] == [0.0, -1.0, 0.0]
    assert "object:plant" in graph.nodes["compose"][0].inputs
    with pytest.raises(ValueError, match=r"cut_and_paste needs each object's .* \['plant'\] are given as trained"):
        build_graph(compose_cfg(["data=folder", objects, "data.backgrounds=photos", "data.test_sets=[]",
                                 "variant=cut_and_paste"]), tmp_path)
    with pytest.raises(ValueError, match=r"objects\[mug\]: `splat` .* and `up` only with `splat`"):
        build_graph(compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/mug.mp4, "
                                 "up: [0, 0, 1]}]", "data.backgrounds=photos", "data.test_sets=[]"]), tmp_path)


def test_cluster_launcher_replaces_the_local_one():
    cfg = compose_cfg(["+experiment=ablation", "hydra/launcher=submitit_slurm_cluster"], hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher") and cfg.hydra.launcher.cpus_per_task == 8
    local = compose_cfg(["+experiment=ablation"], hydra_config=True)
    assert local.hydra.launcher._target_.endswith("JoblibLauncher") and local.hydra.launcher.n_jobs == 2


def test_onnx_depth_model_is_keyed_by_content_not_path(tmp_path):
    for name in ("a.onnx", "b.onnx"):
        (tmp_path / name).write_bytes(b"same model bytes")
    keys = []
    for name in ("a.onnx", "b.onnx"):
        graph = build_graph(compose_cfg(["bg_depth.provider=model", f"bg_depth.model={tmp_path / name}"]), ROOT)
        node = graph.nodes["bg_depth"][0]
        assert node.inputs["model"] == tmp_path / name and node.params["model"] == "local"
        keys.append(Engine(tmp_path / "cache").key(node))
    assert keys[0] == keys[1]
    (tmp_path / "b.onnx").write_bytes(b"another model")
    graph = build_graph(compose_cfg(["bg_depth.provider=model", f"bg_depth.model={tmp_path / 'b.onnx'}"]), ROOT)
    assert Engine(tmp_path / "cache").key(graph.nodes["bg_depth"][0]) != keys[0]


def test_stability_seeds_share_the_object_models_and_reseed_the_detector(tmp_path):
    keys = {}
    for seed in (0, 1):
        cfg = compose_cfg(["+experiment=stability", f"run.seed={seed}"])
        engine = Engine(tmp_path / "cache", global_seed=seed, reseed=tuple(map(str, cfg.run.reseed)))
        graph = build_graph(cfg, ROOT)
        keys[seed] = {(n.stage.name, n.item): engine.key(n) for nodes in graph.nodes.values() for n in nodes}
    kept = [k for k in keys[0] if k[0] in ("sample", "frames", "sfm", "splat_train", "extract", "planes")]
    assert kept and all(keys[0][k] == keys[1][k] for k in kept)
    changed = [k for k in keys[0] if k[0] in ("compose", "train_maskrcnn", "eval")]
    assert changed and all(keys[0][k] != keys[1][k] for k in changed)


@pytest.mark.parametrize("override, key", [
    ("run.reseed=[compose,splat_trian]", "run.reseed"), ("run.until=train", "run.until"),
    ("variant.generator=diffusion", "variant.generator"), ("variant.backgrounds=kitchen", "variant.backgrounds"),
    ("data.source=files", "data.source"), ("bg_depth.provider=sidecr", "bg_depth.provider"),
])
def test_an_enumerated_setting_with_another_value_fails_naming_the_choices(override, key):
    """Choices sit next to their fields (stages/contract/choices.py): Hydra refuses the value when composing."""
    assert re.search(rf"Invalid value .*, expected one of \[.*\]\s+full_key: {re.escape(key)}",
                     composition_error([override]))


@pytest.mark.parametrize("variant", ["full", "cut_and_paste"])
def test_generator_gets_the_inputs_it_declares(variant):
    cfg = compose_cfg([f"variant={variant}"])
    generator = GENERATORS[cfg.variant.generator]
    dataset = build_graph(cfg, ROOT).nodes[generator.name][0]
    read = {kind: fanned(dataset.inputs, kind) for kind in OBJECT_KINDS + PHOTO_KINDS}
    assert {kind for kind, found in read.items() if found} == set(generator.inputs.object_kinds + generator.inputs.photo_kinds)
    assert sum(map(len, read.values())) == len(dataset.inputs)
    assert len(fanned(dataset.inputs, "background")) == cfg.sample.num_backgrounds


def test_default_splat_budget_is_the_schema_default():
    budget = OmegaConf.to_container(OmegaConf.load(CONF / "splat_train" / "default.yaml"))
    assert budget == {key: getattr(SplatTrainConfig(), key) for key in budget}


@pytest.mark.parametrize("variant, ends", [("full", ["train_maskrcnn"]),
                                           ("cut_and_paste", ["planes", "train_maskrcnn"])])
def test_without_test_sets_the_run_ends_with_the_detector(variant, ends):
    graph = build_graph(compose_cfg([f"variant={variant}", "data.test_sets=[]"]), ROOT)
    assert sorted({node.stage.name for node in graph.targets(None)}) == ends


def test_every_stage_of_the_graph_can_end_a_run():
    graph = build_graph(compose_cfg([]), ROOT)
    assert {name for name in ORDER if graph.targets(name)} == set(ORDER) - {"cut_and_paste", "bg_frames"}
    assert build_graph(compose_cfg(["variant=full_walk"]), ROOT).targets("bg_frames")


@pytest.mark.parametrize("variant", ["full_walk", "cut_and_paste_walk"])
def test_the_walk_variants_compose_on_the_frames_of_the_sample_walk(variant, tmp_path):
    """variant.backgrounds=walk: one bg_frames node on the sample's walk video, min(bg_frames.count, its frames)
    slots known before anything runs, each with the ray tracer's depth and the walk's camera (no depth model); the
    in-domain variants keep meaning the in-domain photos."""
    cfg = compose_cfg([f"variant={variant}", "bg_frames.count=12"])
    graph = build_graph(cfg, ROOT)
    [walk] = graph.nodes["bg_frames"]
    sample = graph.nodes["sample"][0]
    assert (walk.inputs["video"].node, walk.inputs["video"].subpath) == (sample, "walk/walk.mp4")
    assert walk.inputs["depth"].subpath == "walk/depth"
    slots = graph.nodes["bg_depth"]
    assert [n.item for n in slots] == [f"walk#{k}" for k in range(12)]
    assert slots[5].inputs["image"].node is walk and slots[5].inputs["image"].subpath == "images/0005.png"
    assert slots[5].inputs["depth"].subpath == "images/0005.depth.png"
    assert slots[5].inputs["intrinsics"].subpath == "walk/walk.json" and slots[5].params["model"] == "none"
    assert len(fanned(graph.nodes[GENERATORS[cfg.variant.generator].name][0].inputs, "background")) == 12
    many = build_graph(compose_cfg([f"variant={variant}", "bg_frames.count=1000"]), ROOT)
    assert len(many.nodes["bg_depth"]) == cfg.sample.walk_seconds * cfg.sample.fps == 160  # the walk's frames
    indomain = build_graph(compose_cfg(["variant=full_indomain"]), ROOT)
    assert "bg_frames" not in indomain.nodes and len(indomain.nodes["bg_depth"]) == cfg.sample.num_indomain
    with pytest.raises(ValueError, match="variant.backgrounds=walk composes on the frames of the sample's walk"):
        build_graph(compose_cfg([f"variant={variant}", "data=folder"]), tmp_path)


@pytest.mark.parametrize("given", ["videos/room.mp4", "[videos/room.mp4]", "[photos,videos/room.mp4]"])
def test_backgrounds_take_a_folder_a_video_or_a_list_of_them(given, tmp_path, cached_depth_model):
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "room.mp4").write_bytes(b"no header read at planning time gives no frame: no slot")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "desk.jpg").write_bytes(b"photo")
    for key in ("backgrounds", "indomain_backgrounds"):
        cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/room.mp4}]",
                           f"data.{key}={given}", "data.test_sets=[]",
                           *(["variant=full_indomain"] if key.startswith("indomain") else [])])
        graph = build_graph(cfg, tmp_path)
        assert [n.inputs["video"] for n in graph.nodes["bg_frames"]] == [tmp_path / "videos" / "room.mp4"]
        assert [n.item for n in graph.nodes.get("bg_depth", [])] == (["desk"] if "photos" in given else [])


@pytest.mark.parametrize("given", ["3", "[photos,[a,b]]", "{folder: photos}"])
def test_backgrounds_of_another_type_fail_at_start_naming_the_setting(given, tmp_path):
    cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: mug.mp4}]",
                       f"data.indomain_backgrounds={given}", "data.backgrounds=photos", "data.test_sets=[]"])
    with pytest.raises(ValueError, match="data.indomain_backgrounds must be a folder of photos, a video file or a "
                                         "list of them, got"):
        build_graph(cfg, tmp_path)


def test_the_frames_of_a_users_video_go_to_the_depth_model(tmp_path, cached_depth_model):
    """Slots sized from the video's header (without decoding it) go through the depth model like a photo without
    a sidecar; a <stem>.json beside the video gives their intrinsics."""
    video = noise_video(tmp_path / "room.mp4", 7, 64, 48)
    (tmp_path / "room.json").write_text('{"K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]]}')
    cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: room.mp4}]",
                       f"data.backgrounds={video}", "data.test_sets=[]"])
    slots = build_graph(cfg, tmp_path).nodes["bg_depth"]
    assert [n.item for n in slots] == [f"room#{k}" for k in range(7)]  # min(bg_frames.count, its 7 frames)
    assert all("model" in n.inputs and "depth" not in n.inputs for n in slots)
    assert slots[0].inputs["intrinsics"] == tmp_path / "room.json"
