"""The experiments command: a tiny report end to end, its resume, and one-line errors for bad options."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import DEMO_CACHE, demo_parser

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.experiments.cli import ExperimentsConfig

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

METHODS = ("continual-ngp", "continual-ngp-incre", "continual-nerf-joint")


def tiny_experiments(output_dir: Path, **options) -> ExperimentsConfig:
    settings = dict(
        dataparser=demo_parser(num_frames=16), output_dir=output_dir, methods=METHODS, num_tasks=2,
        iterations_per_task=3, time_budgets=(0.3,), time_budget_methods=("continual-ngp",), task_counts=(2, 3),
        task_count_methods=("continual-ngp",), rays_per_batch=64,
    )  # fmt: skip
    return ExperimentsConfig(**{**settings, **options})


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory) -> Path:
    output = tmp_path_factory.mktemp("experiments") / "report"
    tiny_experiments(output).main()
    return output


def _run_folders(report_dir: Path) -> set:
    return {path.parent for path in (report_dir / "runs").glob(f"*/*/*/{ACCURACY_MATRIX_FILENAME}")}


def _markdown_rows(text: str, heading: str) -> list:
    """Cells of the table under the '## heading...' line."""
    section = text.split(f"## {heading}", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")]
    return [[cell.strip() for cell in row.strip("|").split("|")] for row in rows[1:]]


def test_report_files_and_figures_come_from_this_run(report_dir):
    results = json.loads((report_dir / "results.json").read_text())
    assert (report_dir / "report.md").exists() and (report_dir / "settings.json").exists()
    figures = results["figures"]
    paths = [figures["fig6"], figures["render_strip"], *figures["accuracy_matrices"].values()]
    assert len(paths) == 2 + len(METHODS)
    report = (report_dir / "report.md").read_text()
    for path in paths:
        assert (report_dir / path).read_bytes().startswith(b"\x89PNG") and f"]({path})" in report
    assert [row["method"] for row in results["table1"]] == list(METHODS)
    assert len(results["runs"]) == len(METHODS) + 2, "table 3's 2-task continual-ngp run is table 1's"
    for run in results["runs"].values():
        matrix = AccuracyMatrix.read(report_dir / run["run_dir"] / ACCURACY_MATRIX_FILENAME)
        assert matrix.finished and matrix.psnr == run["psnr"], "results.json holds the run's own accuracy matrix"
        assert len(run["renders"]) == run["num_tasks"] and all((report_dir / p).exists() for p in run["renders"])
        assert len(run["task_train_seconds"]) == run["num_tasks"] and run["wall_seconds"] > run["train_seconds"] > 0


def test_numbers_in_report_md_equal_results_json(report_dir):
    results = json.loads((report_dir / "results.json").read_text())
    report = (report_dir / "report.md").read_text()
    table1 = _markdown_rows(report, "Table 1")
    assert [row[0] for row in table1] == list(METHODS)
    for row, entry in zip(table1, results["table1"]):
        assert [float(cell) for cell in row[2:]] == [entry[key] for key in
            ("final_mean_psnr", "final_mean_ssim", "train_seconds", "wall_seconds")]  # fmt: skip
        assert entry["final_mean_psnr"] == round(results["runs"][entry["run"]]["mean_psnr"][-1], 2)
    for row, entry in zip(_markdown_rows(report, "Table 2"), results["table2"], strict=True):
        assert (float(row[2]), int(row[3]), float(row[4])) == (
            entry["seconds_per_task"],
            entry["iterations"],
            entry["final_mean_psnr"],
        )
    for row, entry in zip(_markdown_rows(report, "Table 3"), results["table3"], strict=True):
        assert (int(row[2]), float(row[3])) == (entry["num_tasks"], entry["final_mean_psnr"])
    for row, entry in zip(_markdown_rows(report, "Table 4"), results["table4"], strict=True):
        assert [float(cell) for cell in row[2:]] == entry["per_task_psnr"]
    for row, entry in zip(_markdown_rows(report, "Forgetting"), results["forgetting"], strict=True):
        expected = [entry["average_final_psnr"], entry["backward_transfer"], *(entry["per_task"] or [None])]
        assert [None if cell == "n/a" else float(cell) for cell in row[2:]] == expected


def test_forgetting_and_fig6_follow_the_accuracy_matrix(report_dir):
    results = json.loads((report_dir / "results.json").read_text())
    for entry, run_key in zip(results["forgetting"], results["plan"]["table1"]):
        run = results["runs"][run_key]
        curve = results["fig6"]["curves"][run["method"]]
        if run["joint"]:
            assert entry["per_task"] is None and curve["tasks_trained"] == [1, 2]
        else:
            assert entry["per_task"] == [round(run["psnr"][0][0] - run["psnr"][1][0], 2)]
            assert curve["tasks_trained"] == [2] and curve["psnr"] == [round(run["psnr"][1][1], 2)]


def test_rerun_resumes_without_training_finished_runs_again(report_dir):
    before = json.loads((report_dir / "results.json").read_text())
    folders = _run_folders(report_dir)
    after = tiny_experiments(report_dir).main()
    assert _run_folders(report_dir) == folders
    for table in ("table1", "table2", "table3", "table4", "forgetting"):
        assert after[table] == before[table]


def test_other_settings_in_a_report_folder_are_refused(report_dir):
    report = (report_dir / "report.md").read_text()
    with pytest.raises(SystemExit) as exit_info:
        tiny_experiments(report_dir, rays_per_batch=32).main()
    assert str(exit_info.value.code) == (
        f"continual-nerf-experiments: error: --output-dir {report_dir} holds a report made with other rays_per_batch; "
        "choose another --output-dir"
    )
    assert (report_dir / "report.md").read_text() == report


BAD_OPTIONS = [
    ({"methods": ("continual-ngp", "nerfacto-continual")}, "--methods: unknown method 'nerfacto-continual'"),
    ({"time_budget_methods": ("nope",)}, "--time-budget-methods: unknown method 'nope'"),
    ({"methods": ()}, "--methods must name at least one method"),
    ({"iterations_per_task": 0}, "--iterations-per-task must be at least 1, got 0"),
    ({"seconds_per_task": 0.0}, "--seconds-per-task must be positive, got 0.0"),
    ({"time_budgets": (1.0, 0.0)}, "--time-budgets must all be positive, got 1 0"),
    ({"probe_task": 3}, "--probe-task must be between 1 and --num-tasks (2), got 3"),
    ({"task_counts": (2, 9)}, "--task-counts 9 does not fit the scene's 16 frames"),
    (
        {"dataparser": dataclasses.replace(demo_parser(), num_frames=0)},
        "continual-demo --num-frames must be at least 1",
    ),
]


@pytest.mark.parametrize("options,message", BAD_OPTIONS)
def test_bad_option_is_a_one_line_error_and_writes_nothing(tmp_path, options, message):
    output = tmp_path / "report"
    with pytest.raises(SystemExit) as exit_info:
        tiny_experiments(output, **options).main()
    line = str(exit_info.value.code)
    assert line.startswith(f"continual-nerf-experiments: error: {message}") and "\n" not in line
    assert not output.exists()


def test_command_line_error_has_no_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "continual_nerf.experiments", "--output-dir", str(tmp_path / "report"),
         "--iterations-per-task", "0", "continual-demo", "--data", str(DEMO_CACHE), "--num-frames", "16"],
        check=False, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode != 0 and "Traceback" not in result.stderr + result.stdout
    assert result.stderr.strip().splitlines()[-1] == (
        "continual-nerf-experiments: error: --iterations-per-task must be at least 1, got 0"
    )
