"""The benchmarks' grid (bench.grid, bench.quality, bench.throughput): recipes as ns-train arguments, every run's
options, runs read back only when trained with the same arguments."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import DEMO_CACHE
from PIL import Image

from continual_nerf.bench import grid
from continual_nerf.bench.grid import Recipe, RunSummary, Setting, folder_name, parse_recipe, with_options
from continual_nerf.bench.quality import JOINT, RECIPES, QualityBenchmark, plot_quality, series, total
from continual_nerf.bench.results import with_tasks
from continual_nerf.bench.throughput import ThroughputBenchmark
from continual_nerf.core.accuracy_matrix import AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainer
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP


def config_of(bench: QualityBenchmark, recipe: Recipe, scene: str = "room", setting: str = "3x7"):
    (run,) = bench.runs(scene, Setting.parse(setting), [recipe])
    return bench.config(run)


def test_a_variant_is_the_registered_method_with_its_options_as_ns_train_parses_them(tmp_path: Path):
    recipe = parse_recipe(
        "joint, big=continual-ngp-joint --pipeline.model.log2-hashmap-size 19 --pipeline.model.use-color-transform True"
    )
    assert recipe.name == "joint, big"
    config = config_of(QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out"), recipe, "street")
    assert config.method_name == "continual-ngp-joint" and config.pipeline.datamanager.joint
    assert config.pipeline.model.log2_hashmap_size == 19
    assert config.pipeline.model.use_color_transform, "a boolean takes its value, as with ns-train"
    assert config.pipeline.datamanager.num_tasks == 3 and config.pipeline.datamanager.iterations_per_task == 7
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig) and demo.scene == "street" and demo.exposure_segments == 3


def test_a_depth_variant_trains_continual_ngp_depth_on_the_demos_flawed_depth(tmp_path: Path):
    recipe = parse_recipe(
        "depth, kinect=continual-ngp-depth --pipeline.model.depth-loss-mult 0.3 "
        "continual-demo --depth-noise 0.0015 --depth-max-range 4 --depth-edge-holes 1 --depth-dropout 0.05"
    )
    config = config_of(QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out"), recipe)
    assert (
        isinstance(config.pipeline.model, ContinualNGPDepthModelConfig) and config.pipeline.model.depth_loss_mult == 0.3
    )
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig)
    assert (demo.depth_noise, demo.depth_max_range, demo.depth_edge_holes, demo.depth_dropout) == (0.0015, 4, 1, 0.05)


def test_every_runs_options_reach_the_method_and_the_demo_beside_the_recipes_own(tmp_path: Path):
    bench = QualityBenchmark(
        data=tmp_path / "demo",
        output_dir=tmp_path / "out",
        options=("--machine.seed 7 continual-demo --num-frames 30", "--pipeline.lr-decay-start 0.5"),
    )
    recipe = Recipe.of("exposed", "continual-ngp continual-demo --exposure-strength 0.3")
    config = config_of(bench, recipe)
    assert config.machine.seed == 7 and config.pipeline.lr_decay_start == 0.5
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig)
    assert (demo.exposure_strength, demo.num_frames) == (0.3, 30)


def test_a_recipe_that_sets_its_rays_per_batch_trains_with_them_and_the_others_with_the_benchmarks(tmp_path: Path):
    bench = QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out", rays_per_batch=256)
    more_replay = config_of(bench, Recipe.of("more replay", RECIPES["continual-ngp, 3x replayed rays"]))
    assert more_replay.pipeline.datamanager.train_num_rays_per_batch == 2048
    assert more_replay.pipeline.datamanager.current_task_fraction == 0.25
    assert config_of(bench, Recipe.of("plain", "continual-ngp")).pipeline.datamanager.train_num_rays_per_batch == 256
    # the registered method's own number, asked for outright, wins over the benchmark's too
    paper_batch = Recipe.of("paper batch", "continual-ngp --pipeline.datamanager.train-num-rays-per-batch 1024")
    assert config_of(bench, paper_batch).pipeline.datamanager.train_num_rays_per_batch == 1024


def test_options_are_put_before_and_after_the_demo_subcommand():
    assert with_options(["continual-ngp", "--a", "1"], ["--b 2"]) == ["continual-ngp", "--a", "1", "--b", "2"]
    assert with_options(["m", "continual-demo", "--x", "1"], ["--b 2 continual-demo --y 3", "--c 4"]) == [
        "m", "--b", "2", "--c", "4", "continual-demo", "--x", "1", "--y", "3",
    ]  # fmt: skip


@pytest.mark.parametrize(
    "text, message",
    [
        ("no method here", "expected NAME=METHOD [OPTIONS]"),
        ("x=", "expected NAME=METHOD [OPTIONS]"),
        ("x=nerfacto", "x: nerfacto is not a registered continual method"),
        ("x=continual-ngp --pipeline.model.no-such-option 3", "x: --pipeline.model.no-such-option 3 are not options"),
    ],
)
def test_a_bad_variant_ends_with_one_line(text: str, message: str):
    with pytest.raises(SystemExit, match=re.escape(message)) as exit_info:
        parse_recipe(text)
    assert "\n" not in str(exit_info.value.code)


@pytest.mark.parametrize(
    "variants, taken",
    [
        (("continual-ngp=continual-ngp",), "continual-ngp"),
        (("big table=continual-ngp", "bigtable=continual-ngp"), "bigtable"),
    ],
)
def test_a_variant_may_not_take_a_name_or_run_folder_already_taken(tmp_path: Path, variants, taken: str):
    benchmark = QualityBenchmark(recipes=(), variants=variants, output_dir=tmp_path / "out", data=tmp_path / "demo")
    with pytest.raises(SystemExit, match=f"--variants {taken}: a recipe has that name"):
        benchmark.main()


def test_run_folders_are_names_without_separators():
    assert folder_name("table 2^19 / big") == "table2^19big"
    assert folder_name("clean | codes per image") == "clean_codesperimage"
    assert [folder_name(name) for name in RECIPES][:3] == [
        "continual-ngp",
        "continual-ngp_paperrecipe",
        "continual-ngp_ER1%",
    ]


def test_every_recipe_parses_and_the_bound_falls_as_continual_ngp_does(tmp_path: Path):
    bench = QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out")
    configs = {
        recipe.name: bench.config(run)
        for recipe in bench.chosen_recipes()
        for run in bench.runs("room", Setting.parse("2x3"), [recipe])
    }
    assert list(configs) == list(RECIPES)
    joint = configs[JOINT].pipeline
    assert (joint.lr_decay_per_task, joint.lr_decay_start) == (
        CONTINUAL_NGP.pipeline.lr_decay_per_task,
        CONTINUAL_NGP.pipeline.lr_decay_start,
    )
    assert configs[JOINT].pipeline.datamanager.joint
    kinect, stereo = (configs[f"continual-ngp-depth, {flaws} flaws"].pipeline.datamanager.dataparser
                      for flaws in ("sensor", "stereo"))  # fmt: skip
    assert (kinect.depth_max_range, stereo.depth_max_range) == (4, 40), "each recipe's sensor reaches as far as it does"


def matrix_of(rows: list) -> AccuracyMatrix:
    matrix = AccuracyMatrix(num_tasks=len(rows))
    for step, row in enumerate(rows):
        matrix.add_row(row, [0.9] * len(row), sum(row) / len(row), step)
    return matrix


def test_a_finished_run_is_read_back_and_one_of_other_arguments_rays_per_batch_or_device_is_refused(tmp_path: Path):
    bench = QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out")
    (run,) = bench.runs("room", Setting.parse("2x3"), [Recipe.of("a", "continual-ngp")])
    summary = RunSummary.of(matrix_of([[30.0], [29.0, 32.0]]), train_seconds=1.0)
    run.folder.mkdir(parents=True)
    run.summary_path.write_text(json.dumps({"arguments": list(run.arguments), "summary": dataclasses.asdict(summary)}))
    (read,) = bench.summaries([run])  # nothing to train: a training process would fail without a demo scene
    assert read.final_mean_psnr == pytest.approx(30.5) and read.final_row == [29.0, 32.0]
    other = bench.runs("room", Setting.parse("2x3"), [Recipe.of("a", "continual-ngp-paper")])
    with pytest.raises(SystemExit, match="trained as `continual-ngp`, not `continual-ngp-paper`; choose another"):
        bench.summaries(other)
    more_rays = dataclasses.replace(bench, rays_per_batch=2048)
    with pytest.raises(
        SystemExit, match="trained with 1024 rays per batch on cpu, not 2048 rays per batch on cpu; choo"
    ):
        more_rays.summaries([run])
    with pytest.raises(SystemExit, match="summary.json: trained with 1024 rays per batch on cpu, not 1024 .* on cuda"):
        dataclasses.replace(bench, device="cuda").summaries([run])


def test_throughput_times_the_variants_beside_its_own_configurations(tmp_path: Path):
    benchmark = ThroughputBenchmark(
        data=tmp_path / "demo",
        num_tasks=3,
        variants=("table 2^18=continual-ngp --pipeline.model.log2-hashmap-size 18",),
    )
    configs = benchmark.configs(tmp_path / "out")
    assert list(configs) == ["continual-ngp", "continual-ngp-paper", "continual-ngp-incre", "nerfacto", "table 2^18"]
    assert configs["table 2^18"].pipeline.model.log2_hashmap_size == 18
    assert configs["table 2^18"].pipeline.datamanager.num_tasks == 3
    assert configs["continual-ngp"].pipeline.model.log2_hashmap_size == 17


def test_throughput_times_a_variant_at_its_own_rays_per_batch_and_the_others_at_the_benchmarks(tmp_path: Path):
    benchmark = ThroughputBenchmark(
        data=tmp_path / "demo",
        rays_per_batch=512,
        variants=("3x=continual-ngp --pipeline.datamanager.train-num-rays-per-batch 2048", "same=continual-ngp"),
    )
    configs = benchmark.configs(tmp_path / "out")
    rays = {name: config.pipeline.datamanager.train_num_rays_per_batch for name, config in configs.items()}
    assert rays == {
        "continual-ngp": 512,
        "continual-ngp-paper": 512,
        "continual-ngp-incre": 512,
        "nerfacto": 512,
        "3x": 2048,
        "same": 512,
    }


def test_throughput_refuses_a_variant_named_as_its_own_configuration(tmp_path: Path):
    benchmark = ThroughputBenchmark(data=tmp_path / "demo", variants=("nerfacto=continual-ngp",))
    with pytest.raises(SystemExit, match="nerfacto: a configuration has that name already"):
        benchmark.configs(tmp_path / "out")


def test_a_summary_has_each_tasks_psnr_right_after_its_own_training():
    continual = RunSummary.of(matrix_of([[30.0], [29.0, 32.0], [28.0, 31.0, 26.0]]), train_seconds=1.0)
    assert continual.after_own_task == pytest.approx((30.0 + 32.0 + 26.0) / 3)
    assert continual.largest_drop == pytest.approx(2.0) and continual.spread == pytest.approx(5.0)
    joint = RunSummary.of(matrix_of([[20.0, 21.0], [30.0, 31.0]]), train_seconds=1.0)
    assert joint.after_own_task is None, "a joint run's tasks all train from the start: no task has its own training"


def test_a_summary_of_a_run_with_depth_has_its_final_error_and_each_tasks_growth(tmp_path: Path):
    matrix = matrix_of([[30.0], [29.0, 32.0], [28.0, 31.0, 26.0]])
    matrix.depth_abs_rel = [[0.10], [0.11, 0.05], [0.12, None, 0.04]]
    matrix.depth_rmse, matrix.mean_depth_abs_rel, matrix.mean_depth_rmse = [[0.3]] * 3, [0.1, 0.08, 0.07], [0.3] * 3
    summary = RunSummary.of(matrix, train_seconds=1.0)
    assert (summary.final_depth_abs_rel, summary.final_depth_rmse) == (0.07, 0.3)
    assert summary.depth_growth == [pytest.approx(0.2), None, 0.0], "task 1 ends 20 % above its error after task 1"
    colour_only = RunSummary.of(matrix_of([[30.0], [29.0, 32.0]]), train_seconds=1.0)
    assert colour_only.final_depth_abs_rel is None and colour_only.depth_growth is None
    saved = dataclasses.asdict(colour_only)
    for key in ("final_depth_abs_rel", "final_depth_rmse", "depth_growth"):
        del saved[key]
    assert RunSummary(**saved) == colour_only, "a summary.json written before depth reads back"


@pytest.mark.parametrize(("text", "title"), [("1x1200", "1 task x 1200 iterations"), ("5x20s", "5 tasks x 20 s")])
def test_a_setting_titles_its_tables_in_words(text: str, title: str):
    assert str(Setting.parse(text)) == title


@pytest.mark.parametrize("text", ["5", "x240", "0x10", "5x", "fivex240"])
def test_a_bad_setting_is_one_line(text: str):
    with pytest.raises(SystemExit, match="expected TASKSxITERATIONS"):
        Setting.parse(text)


def test_every_pixel_kept_replays_every_closed_tasks_pixels_and_nothing_the_oracle_renders(tmp_path: Path):
    bench = QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out")
    datamanager = config_of(bench, Recipe.of("every pixel kept", RECIPES["every pixel kept"])).pipeline.datamanager
    assert datamanager.replay_buffer_share == 1.0
    buffer = ExperienceReplayBuffer(datamanager.replay_buffer_fraction, datamanager.replay_buffer_pixels)
    flat, rgb = torch.arange(10_000), torch.rand(10_000, 3)
    buffer.add_task(0, flat, rgb, total_pixels=30_000)
    buffer.add_task(1, flat + 10_000, rgb, total_pixels=30_000)
    assert buffer.tasks_held() == {0: 10_000, 1: 10_000}, "two closed tasks, all of their pixels"
    assert CONTINUAL_NGP.pipeline.datamanager.replay_buffer_fraction == 0, "the registered method keeps no pixel"


@pytest.mark.slow
def test_a_tiny_grid_trains_two_recipes_in_two_processes_and_writes_its_tables(tmp_path: Path):
    bench = QualityBenchmark(
        data=DEMO_CACHE,
        output_dir=tmp_path / "out",
        scenes=("room",),
        settings=("2x3",),
        recipes=("continual-ngp", JOINT),
        rays_per_batch=64,
        jobs=2,
        options=("--pipeline.model.num-levels 4 --pipeline.model.log2-hashmap-size 12 continual-demo --num-frames 16 "
                 "--width 24 --height 18",),
    )  # fmt: skip
    bench.main()
    tables = (tmp_path / "out" / "results.md").read_text()
    assert "## room, 2 tasks x 3 iterations" in tables
    rows = [line for line in tables.splitlines() if line.startswith(("| continual-ngp |", f"| {JOINT} |"))]
    assert len(rows) == 2 and rows[1].split(" | ")[2] == "+0.00", "the bound is its own reference"
    saved = json.loads((tmp_path / "out" / "results.json").read_text())["room"]["2x3"]["continual-ngp"]
    assert saved["iterations"] == 6
    assert len(saved["seconds_per_task"]) == 2 and all(seconds > 0 for seconds in saved["seconds_per_task"])
    peaks = saved["peak_mib_per_task"]
    assert len(peaks) == 2 and 0 < peaks[0] <= peaks[1], "each run's own process: its peak, task by task"


def test_a_sweep_over_task_counts_is_plotted_one_line_per_recipe_and_budget(tmp_path: Path):
    def run(psnr: float) -> RunSummary:
        return dataclasses.replace(RunSummary.of(matrix_of([[psnr]]), train_seconds=1.0), final_mean_psnr=psnr)

    results = {
        scene: {key: {"a": run(30.0 - tasks), JOINT: run(31.0)} for key, tasks in (("2x3", 2), ("4x3", 4), ("8x3", 8))}
        for scene in ("room", "street")
    }
    plot_quality(results, tmp_path / "plot.png")
    image = Image.open(tmp_path / "plot.png")
    assert image.size[0] > image.size[1] > 100, "two panels side by side"
    assert len(np.unique(np.asarray(image.convert("RGB")).reshape(-1, 3), axis=0)) > 20, "lines drawn, not blank"
    assert total(Setting.parse("4x3")) == "12 iterations" and total(Setting.parse("4x2.5s")) == "10 s"


def test_the_plot_runs_against_the_budget_per_task_where_the_tasks_are_the_same_and_per_budget_where_not():
    same_tasks = [Setting.parse(key) for key in ("5x60", "5x120", "5x240")]
    assert series(same_tasks, lambda s: float(s.num_tasks)) == {"": [(60.0, 5.0), (120.0, 5.0), (240.0, 5.0)]}
    sweep = [Setting.parse(key) for key in ("2x60", "5x60", "5x120", "10x60")]
    lines = series(sweep, lambda s: 0.0)
    assert set(lines) == {" (60 per task)", " (120 per task)"} and len(lines[" (60 per task)"]) == 3
    fixed_total = [Setting.parse(key) for key in ("2x600", "5x240", "10x120")]
    assert set(series(fixed_total, lambda s: 0.0)) == {" (1200 iterations in all)"}


def test_the_depth_plot_keeps_the_settings_of_its_number_of_tasks():
    results = {scene: {key: {} for key in ("5x60", "5x120", "10x120")} for scene in ("room", "street")}
    assert with_tasks(results, 5) == {"room": {"5x60": {}, "5x120": {}}, "street": {"5x60": {}, "5x120": {}}}  # type: ignore[arg-type]


@pytest.mark.slow
def test_a_run_records_the_commit_checked_out_when_it_started_not_when_it_finished(tmp_path: Path, monkeypatch):
    checked_out = ["started"]
    monkeypatch.setattr(grid, "source_commit", lambda: checked_out[-1])
    train = ContinualTrainer.train

    def train_then_commit(trainer: ContinualTrainer) -> None:
        train(trainer)
        checked_out.append("committed while it trained")

    monkeypatch.setattr(ContinualTrainer, "train", train_then_commit)
    bench = QualityBenchmark(
        data=DEMO_CACHE,
        output_dir=tmp_path / "out",
        rays_per_batch=32,
        options=("--pipeline.model.num-levels 4 --pipeline.model.log2-hashmap-size 12 continual-demo --num-frames 8 "
                 "--width 16 --height 12",),
    )  # fmt: skip
    (run,) = bench.runs("room", Setting.parse("1x2"), [Recipe.of("a", "continual-ngp")])
    grid.train_run(run, bench.config(run))
    assert checked_out[-1] == "committed while it trained", "the run trained through the patched trainer"
    assert grid.read_summary(run, {"rays_per_batch": 32, "device": "cpu"}).commit == "started"
