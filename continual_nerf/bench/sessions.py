"""Sessions: a run that goes on learning a later capture (`--pipeline.continue-with-new-capture`), on both built-in
scenes.

    python -m continual_nerf.bench.sessions [--scenes room street] [--iterations-per-task 240]
        [--changes object-moved wall-repainted] [--runs NAME ...] [--variants "NAME=METHOD OPTIONS" ...]
        [--options="NS-TRAIN OPTIONS"] [--jobs 1] [--output-dir ...]

(a) split: the capture cut into two sessions, its first 3 tasks and then its last 2, the first session's images deleted
    before the second; against one uninterrupted 5-task run of the same budget. Both are measured on every task's test
    frames at the end (the first session's images rendered again for it).
(b) changed: a first session of 3 tasks over the whole path, then a second of 2 tasks that walks the path again after
    a change (continual-demo --laps 2 --change): on views between the path's frames (no run trains on them), PSNR of
    the changed region against the new state and of the rest against the scene as it was (identical there), for
    continual-ngp (with its change guard and without, with its proposal networks relearned, and with the options the
    README gives for moved objects), iNGP-Incre, and the joint bound trained on the new state alone and on both
    walks, each with the budget of the 5 tasks (and on the new state with the later session's 2 tasks); a two-session
    run's unchanged parts also against the end of its first session. `--variants` adds two-session runs of (b) whose
    later session has options of its own; `--runs` trains and tabulates only the runs named (name "joint bound, new
    state" too for a variant's distance to it).

Every run trains in a process of its own, its sessions one after the other; finished runs are read back, not trained
again, so an interrupted benchmark resumes. `results.md` and `results.json` in the output folder hold the tables.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.utils.eval_utils import eval_setup
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import DemoBenchmark, check_names, recipe_config
from continual_nerf.bench.grid import (
    DEMO,
    folder_name,
    parse_recipe,
    recorded_training,
    refuse_other_training,
    source_commit,
    trained_with,
    with_options,
)
from continual_nerf.bench.run_pool import run_pool
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.evaluation import evaluate_frames
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig, DemoScene, SceneChange
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.nerfstudio_compat import without_lpips
from continual_nerf.recipes import quiet_config, train_like_ns_train

FIRST_TASKS, LATER_TASKS = 3, 2
"""Tasks of the first session and of the second; one uninterrupted run has both."""
VIEW_STRIDE = 2
"""(b) measures every VIEW_STRIDE-th view between two capture instants."""
MEASURES_FILENAME = "measures.json"
"""What a finished run's folder keeps of it for the tables, with the arguments it was trained with."""
JOINT_OPTIONS = (
    f"--pipeline.lr-decay-per-task {CONTINUAL_NGP.pipeline.lr_decay_per_task} "
    f"--pipeline.lr-decay-start {CONTINUAL_NGP.pipeline.lr_decay_start}"
)
"""The joint bound trains as continual-ngp does, every image at once: its rates fall over each task's last quarter."""
MOVED_OBJECT_OPTIONS = (
    "--pipeline.relearn-proposal-networks True",
    "--pipeline.restart-optimizer-moments True",
    "--pipeline.datamanager.current-task-fraction 0.75",
)
"""What the README recommends for a later capture where objects moved."""
ONE_TASK = "continual-ngp, moved-object options, later capture as one task"
"""The row whose later session is one task of the budget of LATER_TASKS."""
TITLE = "Sessions: a trained run learns a later capture"
"""The heading of the benchmark's tables."""
TARGETS = {
    "split": 0.2,
    "changed region": 1.0,
    "unchanged parts": 0.5,
}
"""(a) the two-session run within this many dB of one run; (b) the changed region within this many dB of the joint
bound on the new state, the unchanged parts losing at most this many dB against the end of the first session."""


@dataclass(frozen=True)
class Session:
    """One session of a run: what ns-train trains, on which part of the demo capture."""

    arguments: Tuple[str, ...]
    """METHOD [OPTIONS] as after `ns-train` (the benchmark's --options put in)."""
    demo: Tuple[Tuple[str, Any], ...]
    """continual-demo options of this session's capture (its part of the path, the change, the laps)."""
    num_tasks: int
    """Tasks of the session."""
    iterations_per_task: Optional[int] = None
    """Training iterations of each of its tasks; None: the benchmark's --iterations-per-task."""


@dataclass(frozen=True)
class Run:
    """A run of one or more sessions, each continuing the one before on its own capture, whose folder of images is
    deleted before the next session starts."""

    scene: str
    experiment: str
    """split, or changed-<change>."""
    name: str
    """The name its table row gives it."""
    sessions: Tuple[Session, ...]
    folder: Path
    data: Path
    """Where its sessions' copies of the demo capture are rendered (each deleted before the next session)."""

    def session_dir(self, index: int) -> Path:
        return self.folder / f"session{index + 1}"

    def data_dir(self, index: int) -> Path:
        return self.data / f"session{index + 1}"

    @property
    def arguments(self) -> List[Any]:
        """What the run is trained with, as its measures file keeps it (a session's own iterations per task only where
        it has them: the measures of runs without stay current)."""
        return [
            [list(s.arguments), [list(pair) for pair in s.demo], s.num_tasks, *filter(None, [s.iterations_per_task])]
            for s in self.sessions
        ]


@dataclass
class SessionsBenchmark(DemoBenchmark):
    """Two sessions against one run, and a later session that finds the scene changed, on both built-in scenes."""

    scenes: Tuple[DemoScene, ...] = ("room", "street")
    """Built-in scenes to measure on (continual-demo --scene)."""
    iterations_per_task: int = 240
    """Training iterations of every task (the 5-task runs have 5 x this)."""
    experiments: Tuple[Literal["split", "changed"], ...] = ("split", "changed")
    """(a) split: two sessions against one run; (b) changed: a later session after a change."""
    changes: Tuple[SceneChange, ...] = ("object-moved",)
    """What the later session finds changed in (b) (continual-demo --change)."""
    options: Tuple[str, ...] = ()
    """ns-train options for every run (e.g. --machine.seed 1); continual-demo options after the word continual-demo
    (e.g. "continual-demo --width 32 --height 24 --num-frames 40")."""
    runs: Tuple[str, ...] = ()
    """Which runs to train and tabulate (names as the tables print them, and the variants'); none: every run."""
    variants: Tuple[str, ...] = ()
    """More runs of (b), each NAME=METHOD OPTIONS: two sessions of METHOD whose later session adds OPTIONS (e.g.
    'fraction=continual-ngp --pipeline.datamanager.current-task-fraction 0.75')."""
    jobs: int = 1
    """Runs trained at once, each in a process of its own with cores / jobs threads (unless OMP_NUM_THREADS is set)."""
    output_dir: Path = Path("outputs/bench-sessions")
    """Runs, results.json and results.md; finished runs of the same arguments found here are not trained again."""

    def arguments(self, method: str, *options: str) -> Tuple[str, ...]:
        return tuple(with_options([method, *shlex.split(" ".join(options))], self.options))

    def demo_base(self, scene: str) -> ContinualDemoDataParserConfig:
        """The demo capture every run of `scene` reads, with the options given to every run."""
        config = recipe_config(self.arguments("continual-ngp", DEMO), option="--options")
        demo = config.pipeline.datamanager.dataparser
        assert isinstance(demo, ContinualDemoDataParserConfig)
        return dataclasses.replace(demo, scene=scene)  # type: ignore[arg-type]

    def split_runs(self, scene: str) -> List[Run]:
        """(a): one 5-task run, and the same capture in two sessions."""
        instants = self.demo_base(scene).frames
        cut = round(instants * FIRST_TASKS / (FIRST_TASKS + LATER_TASKS))
        ngp = self.arguments("continual-ngp")
        return [
            self.run(scene, "split", "one run, 5 tasks", Session(ngp, (), FIRST_TASKS + LATER_TASKS)),
            self.run(
                scene,
                "split",
                "two sessions, 3 + 2 tasks",
                Session(ngp, (("end_instant", cut),), FIRST_TASKS),
                Session(ngp, (("start_instant", cut),), LATER_TASKS),
            ),
        ]

    def changed_runs(self, scene: str, change: str) -> List[Run]:
        """(b): two-session runs whose second session walks the path again after `change`, and the joint bounds."""
        lap = self.demo_base(scene).frames
        both = (("laps", 2), ("change", change))
        first, later = (*both, ("end_instant", lap)), (*both, ("start_instant", lap))
        experiment = f"changed-{change}"
        joint = self.arguments("continual-ngp-joint", JOINT_OPTIONS)
        total = FIRST_TASKS + LATER_TASKS

        def two_sessions(
            name: str, method: str, *later_options: str, later_tasks: Tuple[int, Optional[int]] = (LATER_TASKS, None)
        ) -> Run:
            """`later_tasks`: the later session's tasks and their iterations (None: the benchmark's)."""
            return self.run(
                scene,
                experiment,
                name,
                Session(self.arguments(method), first, FIRST_TASKS),
                Session(self.arguments(method, *later_options), later, *later_tasks),
            )

        runs = [
            two_sessions("continual-ngp", "continual-ngp"),
            two_sessions("continual-ngp, change guard off", "continual-ngp", "--pipeline.change-guard off"),
            two_sessions(
                "continual-ngp, proposal networks relearned",
                "continual-ngp",
                "--pipeline.relearn-proposal-networks True",
            ),
            two_sessions("continual-ngp, moved-object options", "continual-ngp", *MOVED_OBJECT_OPTIONS),
            # a later capture at hand in full: its images teach the change together, no task distils the one before
            two_sessions(
                ONE_TASK,
                "continual-ngp",
                *MOVED_OBJECT_OPTIONS,
                later_tasks=(1, LATER_TASKS * self.iterations_per_task),
            ),
            two_sessions("iNGP-Incre", "continual-ngp-incre"),
            self.run(scene, experiment, "joint bound, new state", Session(joint, later, total)),
            # the budget the later session had to learn the change in
            self.run(scene, experiment, "joint bound, new state, 2 tasks", Session(joint, later, LATER_TASKS)),
            self.run(scene, experiment, "joint bound, both walks", Session(joint, both, total)),
        ]
        folders = {run.folder for run in runs}
        for variant in map(parse_recipe, self.variants):
            method, *options = variant.arguments
            run = two_sessions(variant.name, method, shlex.join(options))
            if run.folder in folders:
                raise SystemExit(f"--variants {variant.name}: a run of the benchmark has that name (or run folder)")
            folders.add(run.folder)
            runs.append(run)
        return runs

    def run(self, scene: str, experiment: str, name: str, *sessions: Session) -> Run:
        where = Path(scene) / experiment / folder_name(name)
        return Run(scene, experiment, name, tuple(sessions), self.output_dir / "runs" / where, self.data / where)

    def session_config(self, run: Run, index: int) -> ContinualTrainerConfig:
        """Session `index` of `run` as ns-train would train it, on its own copy of the demo capture, continuing the
        session before it."""
        session = run.sessions[index]
        config = recipe_config(session.arguments, f"run {run.name!r}", rays_per_batch=self.rays_per_batch)
        demo = dataclasses.replace(
            self.demo_base(run.scene),
            data=run.data_dir(index),
            exposure_segments=session.num_tasks,
            **dict(session.demo),
        )
        config = quiet_config(
            config,
            run.session_dir(index),
            device=self.device,
            dataparser=demo,
            num_tasks=session.num_tasks,
            iterations_per_task=session.iterations_per_task or self.iterations_per_task,
        )
        config.timestamp = "run"
        if index > 0:
            config.load_dir = self.session_config(run, index - 1).get_checkpoint_dir()
            config.pipeline.continue_with_new_capture = True
        return config

    def measure(self) -> Dict[str, Any]:
        """Every run's measures, trained where not finished before, grouped by scene and experiment."""
        check_names("changes", self.changes, ("object-moved", "wall-repainted"))
        runs = []
        for scene in self.scenes:
            if "split" in self.experiments:
                runs += self.split_runs(scene)
            if "changed" in self.experiments:
                runs += [run for change in self.changes for run in self.changed_runs(scene, change)]
        check_names("runs", self.runs, dict.fromkeys(run.name for run in runs))
        runs = [run for run in runs if not self.runs or run.name in self.runs]
        configs = [[self.session_config(run, i) for i in range(len(run.sessions))] for run in runs]
        expected = [[trained_with(config) for config in sessions] for sessions in configs]
        pending = [(run, c) for run, c, e in zip(runs, configs, expected) if read_measures(run, e) is None]
        if pending:
            with run_pool(self.jobs) as pool:
                list(pool.map(train_and_measure, *zip(*pending)))
        results: Dict[str, Any] = {}
        for run, e in zip(runs, expected):
            measures = read_measures(run, e)
            assert measures is not None, f"{run.folder}: trained above"
            results.setdefault(run.scene, {}).setdefault(run.experiment, {})[run.name] = measures
        return results

    def main(self) -> None:
        results = self.measure()
        tables = results_tables(results)
        for title, columns, rows in tables:
            print_table(title, columns, rows)
        write_text_atomically(self.output_dir / "results.json", json.dumps(results, indent=1))
        write_text_atomically(self.output_dir / "results.md", markdown(self.command(), tables))
        CONSOLE.print(f"[bold green]Tables: {self.output_dir / 'results.md'}")

    def command(self) -> str:
        """The command that makes these tables."""
        return "python -m continual_nerf.bench.sessions " + shlex.join(self.command_arguments())

    def command_arguments(self) -> List[str]:
        """The options this benchmark was given, as its command line."""
        words = ["--scenes", *self.scenes, "--iterations-per-task", str(self.iterations_per_task)]
        words += ["--experiments", *self.experiments, "--changes", *self.changes]
        words += ["--rays-per-batch", str(self.rays_per_batch), "--device", self.device]
        words += [
            *(["--runs", *self.runs] if self.runs else []),
            *(["--variants", *self.variants] if self.variants else []),
        ]
        # one value after "=": tyro would read a value starting with "--" as an option of its own
        return words + ([f"--options={' '.join(self.options)}"] if self.options else [])


def run_commits(results: Dict[str, Any]) -> List[str]:
    """The commits the runs of `results` (scene -> experiment -> run -> measures) were trained at."""
    return [measures["commit"] for scene in results.values() for runs in scene.values() for measures in runs.values()]


def train_and_measure(run: Run, configs: Sequence[ContinualTrainerConfig]) -> None:
    """Train `run`'s sessions one after the other in this process (each session's images deleted before the next
    starts), then measure it and write its measures."""
    commit = source_commit()  # the code this process imports now, whatever is checked out by the time it finishes
    for folder in (run.folder, run.data):  # an unfinished run of an interrupted benchmark starts over
        shutil.rmtree(folder, ignore_errors=True)
    seconds = []
    for index, config in enumerate(configs):
        CONSOLE.print(f"[bold]{run.scene}, {run.experiment}: training {run.name}, session {index + 1}")
        trainer = train_like_ns_train(config)
        seconds.append(trainer.pipeline.budget.total_seconds)
        del trainer
        if index + 1 < len(configs):
            shutil.rmtree(run.data_dir(index))  # the later session never reads the earlier images
    if run.experiment == "split":
        measures = split_measures(run, configs)
    else:
        measures = changed_measures(configs)
    measures["train_seconds"] = seconds[-1]
    measures["commit"] = commit
    write_measures(run, configs, measures)


def write_measures(run: Run, configs: Sequence[ContinualTrainerConfig], measures: Dict[str, Any]) -> None:
    """Keep `run`'s measures with what its sessions were trained with, for `read_measures` to check."""
    saved = {
        "arguments": run.arguments,
        "sessions": [trained_with(config) for config in configs],
        "measures": measures,
    }
    write_text_atomically(run.folder / MEASURES_FILENAME, json.dumps(saved, indent=1))


def read_measures(run: Run, expected: Sequence[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """The run's measures if it finished with the same arguments and each session's `expected` training (rays per
    batch, device); a folder trained otherwise is refused."""
    path = run.folder / MEASURES_FILENAME
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    if saved.get("arguments") != run.arguments:
        raise SystemExit(f"{path}: trained with other arguments than this benchmark's; choose another --output-dir")
    trained = [recorded_training(session) for session in saved.get("sessions", [{}] * len(run.sessions))]
    refuse_other_training(path, trained, expected)
    return saved["measures"]


def run_config_path(config: ContinualTrainerConfig) -> Path:
    return config.get_base_dir() / "config.yml"


def load_run(config: ContinualTrainerConfig) -> Tuple[ContinualDataManager, torch.nn.Module]:
    """The datamanager and model of a session's latest checkpoint, as ns-eval loads them."""
    with without_lpips():
        _, pipeline, _, _ = eval_setup(run_config_path(config), test_mode="test")
    datamanager = pipeline.datamanager
    assert isinstance(datamanager, ContinualDataManager)
    pipeline.eval()
    return datamanager, pipeline.model


def split_measures(run: Run, configs: Sequence[ContinualTrainerConfig]) -> Dict[str, Any]:
    """Per task the final test PSNR over every task's test frames (a split run's first images rendered again to be
    measured), and their mean over every test frame; the rows the first session ended with."""
    for config in configs[:-1]:
        config.pipeline.datamanager.dataparser.setup().get_dataparser_outputs("train")  # renders the images again
    datamanager, model = load_run(configs[-1])
    dataset = datamanager.eval_dataset
    frames = list(range(len(dataset)))
    psnr = evaluate_frames(model, dataset, frames).psnr  # type: ignore[arg-type]
    tasks = datamanager.test_task_of_frame()
    first = AccuracyMatrix.read(configs[0].get_base_dir() / ACCURACY_MATRIX_FILENAME)
    return {
        "final_row": [float(psnr[tasks == task].mean()) for task in range(int(tasks.max()) + 1)],
        "final_mean_psnr": float(psnr.mean()),
        "first_tasks_after_them": float(np.mean([value for value in first.psnr[FIRST_TASKS - 1] if value is not None])),
    }


def changed_measures(configs: Sequence[ContinualTrainerConfig]) -> Dict[str, Any]:
    """PSNR of the changed region (against the new state) and of the unchanged parts on views between the path's
    frames, which no run trains on, at the run's end and, for a run of two sessions, at the end of its first."""
    demo = configs[-1].pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig)
    views = views_between_frames(demo)
    _, model = load_run(configs[-1])
    measures = region_psnr(model, views)
    if len(configs) > 1:
        _, first_model = load_run(configs[0])
        measures["unchanged_after_first_session"] = region_psnr(first_model, views)["unchanged"]
    return measures


@dataclass
class Views:
    """Views of the changed scene: cameras, their images (the new state) and which of their pixels changed."""

    cameras: Any
    images: List[torch.Tensor]
    changed: List[torch.Tensor] = field(default_factory=list)


def views_between_frames(demo: ContinualDemoDataParserConfig) -> Views:
    """Views halfway between two capture instants of the path (every VIEW_STRIDE-th such place), rendered after the
    change and before it: the path sampled twice as densely is the same path (its draws do not depend on the number of
    instants), whose odd instants no capture has."""
    dense = dataclasses.replace(demo, num_frames=2 * demo.frames - 1, laps=1, start_instant=0, end_instant=None)
    before, after = (
        dataclasses.replace(dense, change=change).setup().get_dataparser_outputs("train")
        for change in ("none", demo.change)
    )
    instants = after.metadata.get("time_group", torch.arange(len(after.image_filenames))).view(-1)
    chosen = torch.nonzero((instants % 2 == 1) & ((instants // 2) % VIEW_STRIDE == 0)).view(-1)
    images, changed = [], []
    for frame in chosen.tolist():
        new, old = image_of(after.image_filenames[frame]), image_of(before.image_filenames[frame])
        images.append(new)
        changed.append((new != old).any(dim=-1))
    return Views(after.cameras[chosen], images, changed)


def image_of(path: Path) -> torch.Tensor:
    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255)


@torch.no_grad()
def region_psnr(model: Any, views: Views) -> Dict[str, float]:
    """PSNR over every changed pixel of the views, and over every unchanged one."""
    errors: Dict[str, List[torch.Tensor]] = {"changed": [], "unchanged": []}
    for index, (image, changed) in enumerate(zip(views.images, views.changed)):
        camera = views.cameras[index : index + 1].to(model.device)
        rendered = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1).cpu()
        squared = ((rendered - image) ** 2).mean(dim=-1)
        errors["changed"].append(squared[changed])
        errors["unchanged"].append(squared[~changed])
    return {name: psnr_of(torch.cat(values)) for name, values in errors.items()}


def psnr_of(squared_errors: torch.Tensor) -> float:
    return float(-10 * torch.log10(squared_errors.mean().clamp_min(1e-10)))


Tables = List[Tuple[str, Sequence[str], List[List[str]]]]


def results_tables(results: Dict[str, Any]) -> Tables:
    """Every scene's tables of `SessionsBenchmark.measure`'s results."""
    return [table for scene, experiments in results.items() for table in scene_tables(scene, experiments)]


def scene_tables(scene: str, experiments: Dict[str, Dict[str, Dict[str, Any]]]) -> Tables:
    tables: Tables = []
    for experiment, runs in experiments.items():
        if experiment == "split":
            tables.append((f"{scene}: two sessions against one run", SPLIT_COLUMNS, split_rows(runs)))
        else:
            change = experiment.removeprefix("changed-")
            tables.append((f"{scene}: a later session finds the scene changed ({change})", CHANGED_COLUMNS,
                           changed_rows(runs)))  # fmt: skip
    return tables


SPLIT_COLUMNS = ("run", "tasks 1-3 after task 3 (dB)", "final mean PSNR (dB)", "vs one run (dB)", "final per task (dB)",
                 "training s")  # fmt: skip
CHANGED_COLUMNS = ("run", "changed region (dB)", "vs joint on the new state (dB)", "unchanged parts (dB)",
                   "vs end of first session (dB)")  # fmt: skip


def split_rows(runs: Dict[str, Dict[str, Any]]) -> List[List[str]]:
    one = runs.get("one run, 5 tasks")
    rows = []
    for name, run in runs.items():
        gap = run["final_mean_psnr"] - one["final_mean_psnr"] if one is not None else None
        verdict = "" if gap is None or one is run else (" ok" if abs(gap) <= TARGETS["split"] else " MISSED")
        rows.append([
            name, f"{run['first_tasks_after_them']:.2f}", f"{run['final_mean_psnr']:.2f}",
            "n/a" if gap is None or one is run else f"{gap:+.2f}{verdict}",
            ", ".join(f"{value:.2f}" for value in run["final_row"]), f"{run['train_seconds']:.0f}",
        ])  # fmt: skip
    return rows


def changed_rows(runs: Dict[str, Dict[str, Any]]) -> List[List[str]]:
    joint = runs.get("joint bound, new state")
    rows = []
    for name, run in runs.items():
        to_joint = (
            "n/a"
            if joint is None or run is joint
            else _against(run["changed"] - joint["changed"], -TARGETS["changed region"])
        )
        before = run.get("unchanged_after_first_session")
        lost = "n/a" if before is None else _against(run["unchanged"] - before, -TARGETS["unchanged parts"])
        rows.append([name, f"{run['changed']:.2f}", to_joint, f"{run['unchanged']:.2f}", lost])
    return rows


def _against(difference: float, floor: float) -> str:
    """A difference in dB and whether it meets its target (at least `floor`)."""
    return f"{difference:+.2f} {'ok' if difference >= floor else 'MISSED'}"


def print_table(title: str, columns: Sequence[str], rows: List[List[str]]) -> None:
    table = Table(title=title)
    for column in columns:
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(*row)
    CONSOLE.print(table)


def markdown(command: str, tables: Tables, level: int = 1, provenance: str = "") -> str:
    """The tables under a heading of `level` (#: a page of its own, ##: a section of docs/results.md), with a line
    saying where their numbers come from after the command, if given."""
    lines = [f"{'#' * level} {TITLE}", "", f"`{command}`", "", *([provenance, ""] if provenance else [])]
    lines += [
        f"Targets: (a) two sessions within {TARGETS['split']} dB of one run; (b) the changed region within "
        f"{TARGETS['changed region']} dB of the joint bound on the new state, the unchanged parts losing at most "
        f"{TARGETS['unchanged parts']} dB against the end of the first session.",
        "",
    ]
    for title, columns, rows in tables:
        lines += [f"{'#' * (level + 1)} {title}", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        lines += ["| " + " | ".join(row) + " |" for row in rows] + [""]
    return "\n".join(lines)


def entrypoint() -> None:
    tyro.cli(SessionsBenchmark).main()


if __name__ == "__main__":
    entrypoint()
