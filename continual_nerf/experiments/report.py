"""The experiments report: tables and continual-learning summaries from finished runs, figures, report.md.

Every number in report.md is printed from results.json's tables, which round it first, so the two
always agree; the accuracy matrices in results.json keep full precision.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from continual_nerf.plots import draw_accuracy_matrix  # noqa: E402

PAPER_NAMES = {
    "continual-ngp-paper": "Ours",
    "continual-ngp": "Ours, this plugin's defaults",
    "continual-ngp-incre": "iNGP-Incre",
    "continual-ngp-ewc": "iNGP + EWC",
    "continual-nerf-incre": "NeRF-Incre",
    "continual-nerf-meil": "MEIL-NeRF",
    "continual-ngp-joint": "iNGP*",
    "continual-nerf-joint": "NeRF*",
}
"""The paper's name of each method (Table 1)."""

Run = Dict[str, Any]
"""One run of results.json: its method, budget, accuracy matrix, times and renders."""


def paper_name(method: str) -> str:
    return PAPER_NAMES.get(method, method)


def _r2(value: float) -> float:
    return round(float(value), 2)


def _r1(value: Optional[float]) -> Optional[float]:
    return None if value is None else round(float(value), 1)


def forgetting(run: Run) -> Dict[str, Any]:
    """Average final PSNR, backward transfer and forgetting per task (PSNR just after the task minus at the end)."""
    final = run["psnr"][-1]
    summary: Dict[str, Any] = {"average_final_psnr": _r2(np.mean(final)), "backward_transfer": None, "per_task": None}
    if run["joint"]:  # every task trained from the start: no "just after its own training"
        return summary
    per_task = [run["psnr"][j][j] - final[j] for j in range(len(final) - 1)]
    summary["per_task"] = [_r2(value) for value in per_task]
    summary["backward_transfer"] = _r2(-float(np.mean(per_task))) if per_task else None
    return summary


def probe_curve(run: Run, task: int) -> Dict[str, List[float]]:
    """PSNR of `task` (0-based) after every task-end evaluation that covers it."""
    rows = [(i, row[task]) for i, row in enumerate(run["psnr"]) if len(row) > task]
    return {
        "tasks_trained": [i + 1 for i, _ in rows],
        "steps": [run["steps"][i] + 1 for i, _ in rows],
        "psnr": [_r2(value) for _, value in rows],
    }


def _row(run: Run, **columns: Any) -> Dict[str, Any]:
    """A table row: which method and run it comes from, then its own columns."""
    return {"method": run["method"], "name": paper_name(run["method"]), "run": run["key"], **columns}


def table1(runs: Sequence[Run]) -> List[Dict[str, Any]]:
    return [
        _row(
            run,
            final_mean_psnr=_r2(run["mean_psnr"][-1]),
            final_mean_ssim=round(float(np.mean(run["ssim"][-1])), 3),
            train_seconds=_r1(run["train_seconds"]),
            wall_seconds=_r1(run["wall_seconds"]),
        )
        for run in runs
    ]


def table2(runs: Sequence[Run]) -> List[Dict[str, Any]]:
    return [
        _row(
            run,
            seconds_per_task=run["seconds_per_task"],
            iterations=run["steps"][-1] + 1,
            final_mean_psnr=_r2(run["mean_psnr"][-1]),
        )
        for run in runs
    ]


def table3(runs: Sequence[Run]) -> List[Dict[str, Any]]:
    return [_row(run, num_tasks=run["num_tasks"], final_mean_psnr=_r2(run["mean_psnr"][-1])) for run in runs]


def table4(runs: Sequence[Run]) -> List[Dict[str, Any]]:
    return [_row(run, per_task_psnr=[_r2(value) for value in run["psnr"][-1]]) for run in runs]


def summarize(runs: Dict[str, Run], plan: Dict[str, List[str]], probe_task: int) -> Dict[str, Any]:
    """Every table and summary of the report, from the finished runs named by `plan` (table -> run keys)."""
    main = [runs[key] for key in plan["table1"]]
    return {
        "table1": table1(main),
        "table2": table2([runs[key] for key in plan["table2"]]),
        "table3": table3([runs[key] for key in plan["table3"]]),
        "table4": table4(main),
        "forgetting": [{"method": run["method"], "name": paper_name(run["method"]), **forgetting(run)} for run in main],
        "fig6": {"task": probe_task, "curves": {run["method"]: probe_curve(run, probe_task - 1) for run in main}},
    }


def plot_fig6(fig6: Dict[str, Any], path: Path) -> None:
    figure, axes = plt.subplots(figsize=(6.4, 4.0))
    for method, curve in fig6["curves"].items():
        axes.plot(curve["tasks_trained"], curve["psnr"], marker="o", label=paper_name(method))
    axes.set_xlabel("tasks trained")
    axes.set_ylabel(f"PSNR of task {fig6['task']}'s test frames (dB)")
    axes.set_title(f"Fig. 6: task {fig6['task']} over the course of training")
    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.grid(alpha=0.3)
    axes.legend(fontsize="small")
    _save(figure, path)


def plot_accuracy_matrix(run: Run, path: Path) -> None:
    """Heatmap of R[i][j] (PSNR of task j after training task i), blank above the diagonal for unseen tasks."""
    size = run["num_tasks"]
    rows = len(run["psnr"])
    figure, axes = plt.subplots(figsize=(max(3.6, 1.4 + 0.6 * size), max(2.8, 1.0 + 0.5 * rows)))
    image = draw_accuracy_matrix(axes, run["psnr"], size)
    axes.set_title(f"{paper_name(run['method'])}: PSNR (dB)", fontsize=9)
    figure.colorbar(image, ax=axes, fraction=0.046)
    _save(figure, path)


def plot_render_strip(runs: Sequence[Run], report_dir: Path, probe_task: int, path: Path) -> None:
    """One row per method: the probe view rendered after every task, then its ground truth."""
    columns = max(len(run["renders"]) for run in runs) + 1
    figure, axes = plt.subplots(len(runs), columns, figsize=(1.6 * columns, 1.4 * len(runs) + 0.4), squeeze=False)
    for row, run in zip(axes, runs):
        images = run["renders"] + [run["ground_truth"]]
        titles = [f"after task {i + 1}" for i in range(len(run["renders"]))] + ["ground truth"]
        for axis, image, title in zip(row, images, titles):
            axis.imshow(plt.imread(report_dir / image))
            axis.set_title(title, fontsize=7)
        for axis in row:
            axis.set_xticks([])
            axis.set_yticks([])
        row[0].set_ylabel(paper_name(run["method"]), fontsize=8)
    figure.suptitle(f"First test view of task {probe_task} after each task", fontsize=9)
    _save(figure, path)


def _save(figure: plt.Figure, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def number(value: Optional[float], digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> List[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
        "| " + " | ".join(row) + " |" for row in rows
    ]


def markdown(results: Dict[str, Any]) -> str:
    """report.md: the settings, Tables 1-4, forgetting, and every figure, all from `results`."""
    settings, figures = results["settings"], results["figures"]
    budget = settings["budget"]
    lines = [
        f"# Continual NeRF experiments: {settings['scene']}",
        "",
        f"Command: `{settings['command']}`",
        "",
        f"{settings['num_tasks']} tasks, {budget} per task, {settings['rays_per_batch']} rays per batch, "
        f"model size `{settings['model_size']}`, device `{settings['device']}`, seed {settings['seed']}. "
        "PSNR is the mean over all test frames (every task's held-out frames) unless stated per task. "
        "Training time counts training iterations only, after each run's first (it carries torch's one-off start-up "
        "cost); wall time is the whole run: set-up, training, evaluation at every task end and checkpoints. "
        "The paper trained the NeRF-backbone methods 10x longer per task than the hash-grid ones "
        "(`--implicit-budget-factor 10` does the same).",
        "",
        "## Table 1: final mean test PSNR",
        "",
        *_table(
            ["method", "paper", "PSNR (dB)", "SSIM", "training time (s)", "wall time (s)"],
            [
                [
                    r["method"],
                    r["name"],
                    number(r["final_mean_psnr"]),
                    number(r["final_mean_ssim"], 3),
                    number(r["train_seconds"], 1),
                    number(r["wall_seconds"], 1),
                ]
                for r in results["table1"]
            ],
        ),
        "",
        "## Table 2: time-constrained (training seconds per task)",
        "",
        *_table(
            ["method", "paper", "seconds per task", "iterations trained", "PSNR (dB)"],
            [
                [
                    r["method"],
                    r["name"],
                    f"{r['seconds_per_task']:g}",
                    str(r["iterations"]),
                    number(r["final_mean_psnr"]),
                ]
                for r in results["table2"]
            ],
        ),
        "",
        f"## Table 3: final PSNR by number of tasks ({budget} per task)",
        "",
        *_table(
            ["method", "paper", "tasks", "PSNR (dB)"],
            [[r["method"], r["name"], str(r["num_tasks"]), number(r["final_mean_psnr"])] for r in results["table3"]],
        ),
        "",
        "## Table 4: PSNR of every task after the last task (dB)",
        "",
        *_table(
            ["method", "paper"] + [f"task {j + 1}" for j in range(settings["num_tasks"])],
            [[r["method"], r["name"]] + [number(v) for v in r["per_task_psnr"]] for r in results["table4"]],
        ),
        "",
        "## Forgetting",
        "",
        "Forgetting of task j = its PSNR just after training task j minus its PSNR after the last task; backward "
        "transfer = minus their mean over all tasks but the last. Joint runs train every task from the start: n/a.",
        "",
        *_table(
            ["method", "paper", "average final PSNR", "backward transfer"]
            + [f"forgetting task {j + 1}" for j in range(settings["num_tasks"] - 1)],
            [
                [r["method"], r["name"], number(r["average_final_psnr"]), number(r["backward_transfer"])]
                + (
                    [number(v) for v in r["per_task"]]
                    if r["per_task"] is not None
                    else ["n/a"] * (settings["num_tasks"] - 1)
                )
                for r in results["forgetting"]
            ],
        ),
        "",
        f"## Fig. 6: PSNR of task {results['fig6']['task']} over the course of training",
        "",
        f"![Fig. 6]({figures['fig6']})",
        "",
        "## Accuracy matrices (PSNR of task j after training task i)",
        "",
        *[f"![{method}]({path})" for method, path in figures["accuracy_matrices"].items()],
        "",
        f"## Task {results['fig6']['task']}'s first test view after every task",
        "",
        f"![render strip]({figures['render_strip']})" if figures["render_strip"] else "No run recorded its renders.",
        "",
        "## Runs",
        "",
        *_table(
            ["run", "folder"],
            [[key, f"`{run['run_dir']}`"] for key, run in results["runs"].items()],
        ),
        "",
    ]
    return "\n".join(lines)
