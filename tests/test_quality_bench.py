"""The benchmarks' --variants (bench.quality, bench.throughput): configurations of a user's own, as ns-train options."""

from __future__ import annotations

import copy
import dataclasses
import json
import re
from pathlib import Path

import pytest
import torch

from continual_nerf.bench.demo_runs import parse_variant
from continual_nerf.bench.quality import RECIPES, QualityBenchmark, RunSummary, Setting, folder_name
from continual_nerf.bench.throughput import ThroughputBenchmark
from continual_nerf.core.accuracy_matrix import AccuracyMatrix
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig


def test_a_variant_is_the_registered_method_with_its_options():
    name, config = parse_variant(
        "joint, table 2^19=continual-ngp-joint --pipeline.model.log2-hashmap-size 19 --pipeline.lr-decay-per-task 0.3"
    )
    assert name == "joint, table 2^19"
    assert config.method_name == "continual-ngp-joint"
    assert config.pipeline.datamanager.joint
    assert config.pipeline.model.log2_hashmap_size == 19
    assert config.pipeline.lr_decay_per_task == 0.3


def test_a_variant_run_keeps_its_options_and_takes_the_setting(tmp_path: Path):
    _, variant = parse_variant("big table=continual-ngp --pipeline.model.log2-hashmap-size 19")
    benchmark = QualityBenchmark(data=tmp_path / "demo", output_dir=tmp_path / "out")
    config = benchmark.config("street", Setting.parse("3x7"), (variant, None), tmp_path / "out" / "run")
    assert config.pipeline.model.log2_hashmap_size == 19
    assert config.pipeline.datamanager.num_tasks == 3
    assert config.pipeline.datamanager.iterations_per_task == 7
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig) and demo.scene == "street"


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
        parse_variant(text)
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
    assert [folder_name(name) for name in RECIPES][:3] == [
        "continual-ngp",
        "continual-ngp_paperrecipe",
        "continual-ngp_ER1%",
    ]


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


def test_throughput_refuses_a_variant_named_as_its_own_configuration(tmp_path: Path):
    benchmark = ThroughputBenchmark(data=tmp_path / "demo", variants=("nerfacto=continual-ngp",))
    with pytest.raises(SystemExit, match="nerfacto: a configuration has that name already"):
        benchmark.configs(tmp_path / "out")


def matrix_of(rows: list) -> AccuracyMatrix:
    matrix = AccuracyMatrix(num_tasks=len(rows))
    for step, row in enumerate(rows):
        matrix.add_row(row, [0.9] * len(row), sum(row) / len(row), step)
    return matrix


def test_a_summary_has_each_tasks_psnr_right_after_its_own_training(tmp_path: Path):
    continual = RunSummary.of(matrix_of([[30.0], [29.0, 32.0], [28.0, 31.0, 26.0]]), train_seconds=1.0)
    assert continual.after_own_task == pytest.approx((30.0 + 32.0 + 26.0) / 3)
    assert continual.largest_drop == pytest.approx(2.0) and continual.spread == pytest.approx(5.0)
    joint = RunSummary.of(matrix_of([[20.0, 21.0], [30.0, 31.0]]), train_seconds=1.0)
    assert joint.after_own_task is None, "a joint run's tasks all train from the start: no task has its own training"


def test_a_summary_written_before_the_diagonal_was_kept_takes_it_from_the_runs_matrix(tmp_path: Path):
    matrix = matrix_of([[30.0], [29.0, 32.0]])
    summary = dataclasses.asdict(RunSummary.of(matrix, train_seconds=1.0))
    del summary["after_own_task"]
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    assert RunSummary.read(tmp_path / "summary.json").after_own_task is None, "no matrix beside it: unknown"
    matrix.write(tmp_path / "unnamed" / "continual-ngp" / "2026-01-01_000000")
    assert RunSummary.read(tmp_path / "summary.json").after_own_task == pytest.approx(31.0)


@pytest.mark.parametrize(("text", "title"), [("1x1200", "1 task x 1200 iterations"), ("5x20s", "5 tasks x 20 s")])
def test_a_setting_titles_its_tables_in_words(text: str, title: str):
    assert str(Setting.parse(text)) == title


def test_every_pixel_kept_replays_every_closed_tasks_pixels_and_nothing_the_oracle_renders():
    config, variant = RECIPES["every pixel kept"]
    assert variant is not None
    datamanager = variant(copy.deepcopy(config)).pipeline.datamanager
    assert datamanager.replay_buffer_share == 1.0
    buffer = ExperienceReplayBuffer(datamanager.replay_buffer_fraction, datamanager.replay_buffer_pixels)
    flat, rgb = torch.arange(10_000), torch.rand(10_000, 3)
    buffer.add_task(0, flat, rgb, total_pixels=30_000)
    buffer.add_task(1, flat + 10_000, rgb, total_pixels=30_000)
    assert buffer.tasks_held() == {0: 10_000, 1: 10_000}, "two closed tasks, all of their pixels"
    assert config.pipeline.datamanager.replay_buffer_fraction == 0, "the registered method keeps no pixel"
