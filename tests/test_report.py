"""The report: tables and plots come from the job summaries of a sweep folder."""
from __future__ import annotations

import json
from pathlib import Path

from stages.app.report import mean_std, pareto_front, write_report


def write_job(sweep: Path, num: int, variant: str, seed: int, aps: dict[str, float], seconds: dict[str, float],
              extra: dict | None = None) -> None:
    job = sweep / f"{num}_{variant}"
    job.mkdir(parents=True)
    config = {"variant": {"name": variant}, "run": {"seed": seed},
              "data": {"test_sets": [{"name": "test_a"}, {"name": "test_b"}]}, **(extra or {})}
    evals = {f"{variant}@{test}": {"bbox": {"AP": ap, "AP50": ap + 30,
                                            "per_class": {"bottle": ap + 1, "vase": ap - 1}},
                                   "segm": {"AP": ap - 5}} for test, ap in aps.items()}
    (job / "summary.json").write_text(json.dumps({"variant": {"name": variant}, "config": config, "eval": evals,
                                                  "compute_seconds_by_stage": seconds, "failed": []}))


def test_ablation_report_from_job_summaries(tmp_path):
    write_job(tmp_path, 0, "full", 0, {"test_a": 60.0, "test_b": 50.0}, {"splat_train": 600, "compose": 60})
    write_job(tmp_path, 1, "full", 1, {"test_a": 64.0, "test_b": 52.0}, {"splat_train": 600, "compose": 60})
    write_job(tmp_path, 2, "no_placement", 0, {"test_a": 30.0, "test_b": 20.0}, {"compose": 30})
    write_job(tmp_path, 3, "cut_and_paste", 0, {"test_a": 40.0, "test_b": 35.0}, {"cut_and_paste": 20})
    report = write_report(tmp_path).read_text()
    assert "| Cut-and-Splat | 62.0 ± 2.8 | 51.0 ± 1.4 | 81.21 | 79.68 | 92.0 ± 2.8 | 81.0 ± 1.4 | 57.0 ± 2.8 | 46.0 ± 1.4 |" in report
    assert "| no smart placement | 30.0 | 20.0 | 52.05 | 53.51 | 60.0 | 50.0 | 25.0 | 15.0 |" in report
    assert "| Cut-and-Paste | 40.0 | 35.0 |" in report
    assert "| bottle | 63.0 ± 2.8 | 52.0 ± 1.4 |" in report
    assert (tmp_path / "backgrounds.png").is_file() and (tmp_path / "stage_times.png").is_file()


def test_lead_over_each_variant_is_judged_against_the_seed_spread(tmp_path):
    for seed, (full, paste, placement) in enumerate([(60.0, 40.0, 59.0), (64.0, 44.0, 61.0)]):
        write_job(tmp_path, 3 * seed, "full", seed, {"test_a": full, "test_b": full}, {})
        write_job(tmp_path, 3 * seed + 1, "cut_and_paste", seed, {"test_a": paste, "test_b": paste}, {})
        write_job(tmp_path, 3 * seed + 2, "no_placement", seed, {"test_a": placement, "test_b": placement}, {})
    write_job(tmp_path, 6, "no_aug", 0, {"test_a": 50.0, "test_b": 50.0}, {})
    report = write_report(tmp_path).read_text()
    assert "| Cut-and-Paste | +20.0 (2.8 / 2.8) | yes | +20.0 (2.8 / 2.8) | yes |" in report
    assert "| no smart placement | +2.0 (2.8 / 1.4) | no | +2.0 (2.8 / 1.4) | no |" in report
    assert "| no augmentation | +12.0 | — (one seed) | +12.0 | — (one seed) |" in report


def test_speed_accuracy_report_marks_pareto_front(tmp_path):
    for num, (size, ap, secs) in enumerate([(100, 40.0, 600), (300, 55.0, 900), (200, 39.0, 1200)]):
        write_job(tmp_path, num, "full", 0, {"test_a": ap, "test_b": ap}, {"train_maskrcnn": secs},
                  {"compose": {"num_images": size}})
    report = write_report(tmp_path).read_text()
    assert "Ablation" not in report  # other axes vary: no ablation table
    assert "| 1 | num_images=100 | 10.0 | 40.0 | 1 | yes |" in report
    assert "| 2 | num_images=300 | 15.0 | 55.0 | 1 | yes |" in report
    assert "| 3 | num_images=200 | 20.0 | 39.0 | 1 |  |" in report
    assert (tmp_path / "speed_accuracy.png").is_file()
    assert not (tmp_path / "backgrounds.png").exists()  # one variant at several budgets: no method comparison


def test_speed_accuracy_pools_seeds_and_the_ablation_has_no_speed_chart(tmp_path):
    for num, (seed, ap) in enumerate([(0, 40.0), (1, 44.0)]):
        write_job(tmp_path, num, "full", seed, {"test_a": ap, "test_b": ap}, {"train_maskrcnn": 600},
                  {"train_maskrcnn": {"epochs": 2}})
    write_job(tmp_path, 2, "full", 0, {"test_a": 50.0, "test_b": 50.0}, {"train_maskrcnn": 1200},
              {"train_maskrcnn": {"epochs": 4}})
    report = write_report(tmp_path).read_text()
    assert "| 1 | epochs=2 | 10.0 | 42.0 ± 2.8 | 2 | yes |" in report
    assert "| 2 | epochs=4 | 20.0 | 50.0 | 1 | yes |" in report
    ablation = tmp_path / "ablation"
    write_job(ablation, 0, "full", 0, {"test_a": 60.0, "test_b": 50.0}, {"compose": 60})
    write_job(ablation, 1, "no_aug", 0, {"test_a": 55.0, "test_b": 45.0}, {"compose": 50})
    assert "Speed against accuracy" not in write_report(ablation).read_text()


def test_pareto_front_and_mean_std():
    assert pareto_front([(1, 10), (2, 5), (3, 20), (4, 20)]) == [0, 2]
    assert mean_std([]) == "—" and mean_std([2.0]) == "2.0" and mean_std([1.0, 3.0]) == "2.0 ± 1.4"


def test_empty_sweep_says_so(tmp_path):
    assert "No job summaries" in write_report(tmp_path).read_text()


def test_report_pools_the_jobs_of_a_sweep_run_in_parts(tmp_path):
    first, second = tmp_path / "first", tmp_path / "second"
    write_job(first, 0, "full", 0, {"test_a": 60.0, "test_b": 50.0}, {})
    write_job(second, 0, "full", 1, {"test_a": 64.0, "test_b": 52.0}, {})
    write_job(second, 1, "cut_and_paste", 0, {"test_a": 40.0, "test_b": 35.0}, {})
    report = write_report(first, (second,)).read_text()
    assert f"Sweep folders: `{first}`, `{second}`; 3 jobs." in report
    assert "| Cut-and-Splat | 62.0 ± 2.8 | 51.0 ± 1.4 |" in report and "| Cut-and-Paste | 40.0 | 35.0 |" in report
    assert not (second / "report.md").exists()
