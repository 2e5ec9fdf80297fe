"""The sessions benchmark (bench.sessions): its runs as ns-train would train them, each later session continuing the
one before on its own part of the capture, and its tables against the targets."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from helpers import DEMO_CACHE

from continual_nerf.bench.sessions import (
    MEASURES_FILENAME,
    ONE_TASK,
    SessionsBenchmark,
    changed_rows,
    markdown,
    read_measures,
    run_commits,
    split_rows,
    views_between_frames,
    write_measures,
)
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig


def bench(tmp_path: Path) -> SessionsBenchmark:
    return SessionsBenchmark(
        data=tmp_path / "demo",
        output_dir=tmp_path / "out",
        iterations_per_task=7,
        options=("--machine.seed 3 continual-demo --num-frames 20",),
    )


def demo_of(config) -> ContinualDemoDataParserConfig:
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig)
    return demo


def test_the_split_is_the_first_three_fifths_then_the_rest_each_on_its_own_copy(tmp_path):
    benchmark = bench(tmp_path)
    one, split = benchmark.split_runs("street")
    (whole,) = [benchmark.session_config(one, 0)]
    first, second = (benchmark.session_config(split, index) for index in range(2))
    assert whole.pipeline.datamanager.num_tasks == 5 and whole.load_dir is None
    assert (first.pipeline.datamanager.num_tasks, second.pipeline.datamanager.num_tasks) == (3, 2)
    assert (demo_of(first).end_instant, demo_of(second).start_instant) == (12, 12), "20 instants: 12, then 8"
    assert demo_of(first).data != demo_of(second).data, "the first session's copy can be deleted alone"
    assert demo_of(second).scene == "street" and second.machine.seed == 3
    assert second.load_dir == first.get_checkpoint_dir() and second.pipeline.continue_with_new_capture
    assert second.pipeline.datamanager.iterations_per_task == 7


def test_the_changed_scene_walks_twice_and_the_bounds_train_the_budget_of_both_sessions(tmp_path):
    runs = {run.name: run for run in bench(tmp_path).changed_runs("room", "wall-repainted")}
    moved = "continual-ngp, moved-object options"
    assert set(runs) == {"continual-ngp", "continual-ngp, change guard off", "continual-ngp, proposal networks relearned",
                         moved, ONE_TASK, "iNGP-Incre", "joint bound, new state", "joint bound, new state, 2 tasks",
                         "joint bound, both walks"}  # fmt: skip
    benchmark = bench(tmp_path)
    first, later = (benchmark.session_config(runs["continual-ngp"], index) for index in range(2))
    assert (demo_of(first).laps, demo_of(first).change, demo_of(first).end_instant) == (2, "wall-repainted", 20)
    assert demo_of(later).start_instant == 20, "the second walk, after the change"
    off = benchmark.session_config(runs["continual-ngp, change guard off"], 1)
    assert off.pipeline.change_guard == "off" and later.pipeline.change_guard == "later-sessions"
    relearned = benchmark.session_config(runs["continual-ngp, proposal networks relearned"], 1)
    assert relearned.pipeline.relearn_proposal_networks and not later.pipeline.relearn_proposal_networks
    assert not relearned.pipeline.restart_optimizer_moments and not later.pipeline.restart_optimizer_moments
    moved_later = benchmark.session_config(runs[moved], 1).pipeline
    assert moved_later.relearn_proposal_networks and moved_later.restart_optimizer_moments
    one_task = benchmark.session_config(runs[ONE_TASK], 1).pipeline
    assert one_task.relearn_proposal_networks and one_task.datamanager.current_task_fraction == 0.75
    tasks = (one_task.datamanager.num_tasks, one_task.datamanager.iterations_per_task)
    assert tasks == (1, 2 * moved_later.datamanager.iterations_per_task), "the budget of the later session's 2 tasks"
    assert runs[moved].arguments[1][:2] == runs[ONE_TASK].arguments[1][:2], "the same options, the same capture"
    assert len(runs[moved].arguments[1]) == 3, "a session of the benchmark's iterations keeps its measures current"
    assert benchmark.session_config(runs["iNGP-Incre"], 1).method_name == "continual-ngp-incre"
    new_state = benchmark.session_config(runs["joint bound, new state"], 0)
    both = benchmark.session_config(runs["joint bound, both walks"], 0)
    assert new_state.pipeline.datamanager.joint and new_state.pipeline.datamanager.num_tasks == 5
    assert benchmark.session_config(runs["joint bound, new state, 2 tasks"], 0).pipeline.datamanager.num_tasks == 2
    assert demo_of(new_state).start_instant == 20 and (demo_of(both).start_instant, demo_of(both).end_instant) == (
        0,
        None,
    )


def test_a_variant_adds_two_sessions_whose_later_one_alone_has_its_options_and_rays_per_batch(tmp_path):
    variant = "fraction=continual-ngp --pipeline.datamanager.current-task-fraction 0.75"
    benchmark = dataclasses.replace(bench(tmp_path), variants=(variant,))
    runs = {run.name: run for run in benchmark.changed_runs("room", "object-moved")}
    first, later = (benchmark.session_config(runs["fraction"], index) for index in range(2))
    assert first.pipeline.datamanager.current_task_fraction == 0.5, "the first session is continual-ngp's"
    assert later.pipeline.datamanager.current_task_fraction == 0.75 and later.pipeline.continue_with_new_capture
    assert later.load_dir == first.get_checkpoint_dir()
    assert first.pipeline.datamanager.train_num_rays_per_batch == benchmark.rays_per_batch
    assert later.pipeline.datamanager.train_num_rays_per_batch == benchmark.rays_per_batch
    assert "--variants" in benchmark.command() and variant in benchmark.command_arguments()
    rays = dataclasses.replace(
        benchmark, variants=("rays=continual-ngp --pipeline.datamanager.train-num-rays-per-batch 64",)
    )
    more_rays = {run.name: run for run in rays.changed_runs("room", "object-moved")}["rays"]
    assert rays.session_config(more_rays, 1).pipeline.datamanager.train_num_rays_per_batch == 64, "the variant's own"
    taken = dataclasses.replace(benchmark, variants=("continual-ngp=continual-ngp --machine.seed 4",))
    with pytest.raises(SystemExit, match="--variants continual-ngp: a run of the benchmark has that name"):
        taken.changed_runs("room", "object-moved")


def test_runs_names_the_runs_trained_and_tabulated_and_refuses_others(tmp_path):
    benchmark = dataclasses.replace(bench(tmp_path), scenes=("room",), experiments=("changed",), runs=("iNGP-Incre",))
    (chosen,) = [run for run in benchmark.changed_runs("room", "object-moved") if run.name == "iNGP-Incre"]
    chosen.folder.mkdir(parents=True)  # trained before: read back, and no other run trains
    (chosen.folder / MEASURES_FILENAME).write_text(json.dumps({"arguments": chosen.arguments, "measures": {"x": 1}}))
    assert benchmark.measure() == {"room": {"changed-object-moved": {"iNGP-Incre": {"x": 1}}}}
    unknown = dataclasses.replace(benchmark, runs=("continual-ngp", "joint"))
    with pytest.raises(SystemExit, match=r"--runs: unknown joint \(known: continual-ngp, "):
        unknown.measure()


def test_a_run_is_read_back_only_when_trained_with_the_same_arguments_rays_per_batch_and_device(tmp_path):
    benchmark = bench(tmp_path)
    run = benchmark.split_runs("room")[1]
    on_cpu = [{"rays_per_batch": 1024, "device": "cpu"}] * 2
    assert read_measures(run, on_cpu) is None
    run.folder.mkdir(parents=True)
    measures = run.folder / MEASURES_FILENAME
    measures.write_text(json.dumps({"arguments": run.arguments, "measures": {"x": 1}}))
    assert read_measures(run, on_cpu) == {"x": 1}, "a file older than its training was recorded: 1024 rays on the cpu"
    more_rays = [on_cpu[0], {"rays_per_batch": 2048, "device": "cpu"}]
    with pytest.raises(SystemExit, match=f"{MEASURES_FILENAME}: trained with 1024 rays per batch on cpu; 1024 rays"):
        read_measures(run, more_rays)
    configs = [benchmark.session_config(run, index) for index in range(2)]
    configs[1].pipeline.datamanager.train_num_rays_per_batch = 2048
    write_measures(run, configs, {"x": 2})
    assert read_measures(run, more_rays) == {"x": 2}, "each session's own rays are kept"
    with pytest.raises(
        SystemExit, match="not 1024 rays per batch on cuda; 2048 rays per batch on cuda; choose another"
    ):
        read_measures(run, [{**session, "device": "cuda"} for session in more_rays])
    measures.write_text(json.dumps({"arguments": [], "measures": {"x": 1}}))
    with pytest.raises(SystemExit, match="trained with other arguments"):
        read_measures(run, on_cpu)


def test_the_tables_say_whether_each_target_is_met():
    split = {
        "one run, 5 tasks": {"first_tasks_after_them": 25.0, "final_mean_psnr": 24.0, "final_row": [23.5, 24.5],
                             "train_seconds": 100.0},
        "two sessions, 3 + 2 tasks": {"first_tasks_after_them": 25.0, "final_mean_psnr": 23.7, "final_row": [23.0, 24.4],
                                      "train_seconds": 101.0},
    }  # fmt: skip
    rows = split_rows(split)
    assert rows[0][3] == "n/a" and rows[1][3] == "-0.30 MISSED"
    changed = {
        "continual-ngp": {"changed": 20.5, "unchanged": 25.0, "unchanged_after_first_session": 25.3},
        "iNGP-Incre": {"changed": 19.0, "unchanged": 23.0, "unchanged_after_first_session": 25.3},
        "joint bound, new state": {"changed": 21.0, "unchanged": 26.0},
    }
    rows = changed_rows(changed)
    assert rows[0][2:] == ["-0.50 ok", "25.00", "-0.30 ok"]
    assert rows[1][2:] == ["-2.00 MISSED", "23.00", "-2.30 MISSED"] and rows[2][2] == rows[2][4] == "n/a"
    text = markdown("python -m continual_nerf.bench.sessions", [("room", ("run",), [["x"]])])
    assert "within 0.2 dB of one run" in text and "| x |" in text
    section = markdown("python -m continual_nerf.bench.sessions", [("room", ("run",), [["x"]])], 2, "Generated at `c`.")
    assert section.startswith("## Sessions") and "\n### room\n" in section, "a section of docs/results.md"
    assert section.splitlines()[2:5] == ["`python -m continual_nerf.bench.sessions`", "", "Generated at `c`."]
    measured = {"room": {"split": {"one run": {"commit": "a"}}, "changed": {"joint": {"commit": "b"}}}}
    assert run_commits(measured) == ["a", "b"]


@pytest.mark.parametrize("scene", ["room", "street"])
def test_the_changed_scene_is_measured_between_the_frames_any_run_trains_on(scene):
    demo = ContinualDemoDataParserConfig(data=DEMO_CACHE, scene=scene, num_frames=8, width=24, height=18,
                                         change="object-moved", laps=2, start_instant=8)  # fmt: skip
    capture = demo.setup().get_dataparser_outputs("train")
    dense = dataclasses.replace(demo, num_frames=15, laps=1, start_instant=0).setup().get_dataparser_outputs("train")
    cameras = len(capture.image_filenames) // 8
    even = torch.cat([torch.arange(2 * i * cameras, (2 * i + 1) * cameras) for i in range(8)])
    assert torch.allclose(dense.cameras.camera_to_worlds[even], capture.cameras.camera_to_worlds, atol=1e-6), (
        "the even instants of the path sampled twice as densely are the capture's"
    )
    views = views_between_frames(demo)
    assert len(views.images) == 4 * cameras, "instants 1, 5, 9 and 13 of 15"
    assert any(bool(changed.any()) for changed in views.changed) and all(
        changed.float().mean() < 0.5 for changed in views.changed
    )
