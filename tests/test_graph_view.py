"""`python dag.py run.action=graph`: the stage graph as Mermaid text (stages/app/graph_view.py), the README's picture
of the DAG, and the cached nodes marked."""
from __future__ import annotations

import re
from pathlib import Path

from stages.app.graph_view import mermaid
from stages.app.pipeline import build_graph
from stages.engine.cache_entry import Outcome
from tests.factories.configs import compose_cfg, run_dag

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_draws_the_default_graph():
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```mermaid\n(.*?)\n```", readme, re.S)
    assert blocks == [mermaid(build_graph(compose_cfg([]), ROOT))], "regenerate: python dag.py run.action=graph"


def test_boxes_fan_out_and_arrows_follow_the_inputs():
    text = mermaid(build_graph(compose_cfg(["variant=cut_and_paste"]), ROOT))
    assert 'frames["frames<br/>5 objects"]' in text and 'bg_depth["bg_depth<br/>40 photos"]' in text
    assert 'cut_and_paste["cut_and_paste<br/>4 shards"]' in text and "compose" not in text
    assert 'dataset["dataset<br/>1 variant"]' in text and "    cut_and_paste --> dataset" in text
    assert "    sfm --> cut_and_paste" in text and "    extract --> cut_and_paste" in text
    assert "    planes --> cut_and_paste" not in text  # Cut-and-Paste places nothing on planes
    assert "classDef" not in text


def test_the_status_marks_cached_stages():
    graph = build_graph(compose_cfg([]), ROOT)
    plan = [Outcome(node.stage.name, node.item, "k", "cached" if node.stage.name in ("sample", "frames") or
                   node.item == "bottle" else "would-run") for nodes in graph.nodes.values() for node in nodes]
    text = mermaid(graph, plan)
    assert 'sfm["sfm<br/>5 objects<br/>1/5 cached"]' in text
    assert "    class frames cached" in text and "    class sfm partly" in text and "class compose" not in text


def test_dag_prints_and_writes_the_graph(tmp_path):
    done, _ = run_dag("run.action=graph", "run.graph_status=true", f"run.cache_dir={tmp_path / 'cache'}",
                      cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("flowchart LR\n") and "0/5 cached" in done.stdout
    assert (tmp_path / "run" / "graph.mmd").read_text() == done.stdout


def test_a_walk_variant_draws_its_video_and_counts_empty_slots_as_done():
    graph = build_graph(compose_cfg(["variant=full_walk"]), ROOT)
    plan = [Outcome(node.stage.name, node.item, "k", "empty" if node.item == "walk#19" else "cached")
            for nodes in graph.nodes.values() for node in nodes]
    text = mermaid(graph, plan)
    assert 'bg_frames["bg_frames<br/>1 video<br/>1/1 cached"]' in text and "    sample --> bg_frames" in text
    assert "    bg_frames --> bg_depth" in text and "    bg_frames --> planes" in text
    assert 'bg_depth["bg_depth<br/>20 photos<br/>20/20 cached"]' in text and "    class bg_depth cached" in text
