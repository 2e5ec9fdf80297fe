"""docs/results.md and the README's results table, regenerated: the current code's numbers, replaced, never appended.

    python -m continual_nerf.bench.results [--jobs 2] [--device cpu] [--output-dir outputs/results]
        [--sections quality default-budget distillation-weight depth sweep real-capture sessions]

Trains (or reads back from `--output-dir`, so an interrupted run resumes) the quality benchmark's main recipes on both
demo scenes at 5 x 240 and 10 x 120, continual-ngp and every pixel kept at the default 10 x 1000, the distillation
weights, the depth recipes at 5 x 60, 5 x 120, 5 x 240 and 10 x 120, the long street's task-count sweep against every
pixel kept, the real-capture benchmark's flaws with the features the README recommends for them and the sessions
benchmark on both scenes, then rewrites `docs/results.md` and the table between the README's `results` markers. Each
section names the benchmark command that makes it alone; `--sections` regenerates only those named and keeps the
page's others word for word.
"""

from __future__ import annotations

import os
import platform
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Mapping, Sequence, Tuple

import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench import quality, real_capture, sessions
from continual_nerf.bench.demo_runs import Device, check_names
from continual_nerf.bench.grid import RunSummary, Setting, source_commit
from continual_nerf.bench.run_pool import threads_per_run
from continual_nerf.dataparsers.continual_demo_dataparser import DemoScene

QUALITY_SETTINGS = ("5x240", "10x120")
"""The quality grid's settings: five tasks, and ten tasks of half the budget (the same 1200 iterations)."""
QUALITY_RECIPES = ("continual-ngp", "continual-ngp, paper recipe", "every pixel kept", "iNGP-Incre", quality.JOINT)
"""The quality grid's recipes: the defaults, the paper's recipe, what any replay can reach, no replay, the bound."""
DEFAULT_BUDGET_SETTINGS = ("10x1000",)
"""The paper's setting at the default budget: 10 tasks of 1000 iterations each (--iterations-per-task's default)."""
DEFAULT_BUDGET_RECIPES = ("continual-ngp", "every pixel kept")
"""Replay by distillation against the most any replay can give, at the default budget."""
DEFAULT_BUDGET_NOTE = (
    "The paper's setting at the budget `ns-train continual-ngp` trains by default: 10 tasks of 1000 iterations "
    "(`--pipeline.datamanager.iterations-per-task`), where the grid above gives a task 120 or 240. *every pixel kept* "
    "goes on training a closed task on its own pixels, which replay by distillation cannot; a row's final mean against "
    "its *right after own task* says how much its closed tasks gained or lost after their task."
)
DISTILLATION_RECIPES = ("continual-ngp", "continual-ngp, distillation x2", "every pixel kept")
"""Eq. 4's distillation term at the paper's weight and at twice it, against the most any replay can give."""
DISTILLATION_SETTINGS = QUALITY_SETTINGS + DEFAULT_BUDGET_SETTINGS
"""The quality grid's settings and the default budget, where a closed task has the most iterations to drift."""
DISTILLATION_NOTE = (
    "`--pipeline.model.distillation-loss-mult 2` weighs Eq. 4's distillation term twice the open task's pixels: the "
    "same rays and step time, closed tasks held closer to the replay oracle, the open task a smaller share of each "
    "step. *largest drop from best* says how much a task forgot; *right after own task* how much the open task learned, "
    "and a row's final mean against it what its closed tasks lost or gained after their task: *every pixel kept* gains "
    "by training them further on their own pixels, which replay by distillation cannot."
)
ROOM_CAPTURES = ("clean", "exposure +-30 %", "poses off 1 deg, 1 %")
ROOM_FEATURES = ("off", "colour transform per image", "pose refinement from mid-task")
STREET_CAPTURES = ("clean", "camera responses +-20 %")
STREET_FEATURES = ("off", "codes per image")
SESSIONS_SCENES = ("room", "street")
"""The sessions benchmark's scenes: both built-in ones, as the quality grid's."""
BOUNDS_NOTE = (
    "*every pixel kept*: continual-ngp whose replayed rays all come from a buffer holding every pixel of every closed "
    "task (what the continual setting forbids keeping): the most any replay can give. *joint*: every image from the "
    "first step, the same total iterations. *right after own task*: the mean over tasks of each task's PSNR when its "
    "own training ended."
)
DEPTH_SETTINGS = ("5x60", "5x120", "5x240", "10x120")
"""The depth grid's settings: a quarter, half and all of the main grid's iterations per task (what depth promises:
the quality sooner), and ten tasks of half the budget (whether depth keeps geometry from drifting as tasks add up)."""
DEPTH_PLOT_TASKS = 5
"""The depth plot's settings: those of this many tasks, against their iterations per task (the paper's "instant"
axis)."""
DEPTH_RECIPES = (
    "continual-ngp",
    "continual-ngp-depth",
    "continual-ngp-depth, sensor flaws",
    "continual-ngp-depth, stereo flaws",
    "continual-ngp-depth, geometry not distilled",
    "joint, depth",
)
"""Colour alone, with the demo's exact depth maps, with an indoor depth sensor's flaws and with a car's stereo rig's,
with replayed rays teaching colour only (no geometry distillation), and the joint bound with depth."""
DEPTH_PLOT = "depth.png"
"""The depth grid's plot of PSNR against iterations per task, beside the results page."""
DEPTH_NOTE = (
    "The demo scenes' depth maps: exact, or with a sensor's flaws (noise growing with distance, no depth beyond a "
    "range, holes at edges, dropped pixels): *sensor flaws* an indoor structured-light sensor's (Kinect: nothing beyond "
    "4 m, which leaves a street mostly without depth), *stereo flaws* a car's stereo rig's (nothing beyond 40 m; noise "
    "5 cm at 8.5 m, 1.1 m at 40 m). continual-ngp-depth distils the replay oracle's weights along replayed rays beside "
    "their colour; *geometry not distilled*: their colour only (`--pipeline.model.replay-weights-loss-mult 0`). "
    "*depth abs rel*: mean absolute relative depth error of the final model on the test frames; *largest depth error "
    "growth*: the most any task's depth error grew after its task closed."
)
SWEEP_SETTINGS = ("2x120", "5x120", "10x120", "20x120", "40x120")
"""The task-count sweep: the long street in 2 to 40 tasks at a fixed budget per task."""
SWEEP_RECIPES = ("continual-ngp", "continual-ngp, distillation x2", "every pixel kept")
"""Replay by distillation at the paper's weight and at twice it, against the most any replay can give: what
distillation costs as tasks add up."""
SWEEP_NOTE = (
    "The long street (`continual-demo --scene long-street`: 480 rig instants, nothing revisited) cut into 2 to 40 tasks "
    "of 120 iterations each: the more tasks, the more iterations each image gets (120 per task, over fewer images), so "
    "the PSNR rises with the task count where forgetting does not outweigh it. *every pixel kept* against continual-ngp "
    "is what replay by distillation costs at each task count, and `--pipeline.model.distillation-loss-mult 2` how much "
    "of it a heavier distillation term wins back. *s per task* and *peak MiB* from the first task to the last show "
    "what many tasks cost."
)
SWEEP_PLOT = "sweep.png"
"""The sweep's plot of PSNR against the number of tasks, beside the results page."""
README_MARKERS = ("<!-- results: begin -->", "<!-- results: end -->")
"""The README's generated table lies between these lines."""
SECTIONS = ("quality", "default-budget", "distillation-weight", "depth", "sweep", "real-capture", "sessions")
"""The page's sections, in its order; --sections regenerates some and keeps the others as the page has them."""
SECTION_TITLES = {
    "quality": "Continual-ngp against its bounds",
    "default-budget": "Ten tasks at the default budget",
    "distillation-weight": "Distillation's weight",
    "depth": "Depth maps: continual-ngp-depth",
    "sweep": "Long captures: 2 to 40 tasks",
    "real-capture": "Real-capture flaws",
    "sessions": sessions.TITLE,
}
"""Each section's heading (the real-capture flaws' two headings start with theirs)."""
HEADER = (
    "# Results",
    "",
    "Generated by `python -m continual_nerf.bench.results` (each section replaced whole when it is regenerated, "
    "`--sections` choosing which; older numbers are in git history). Every run trains through nerfstudio's Trainer on "
    "the built-in demo scenes (1024 rays per batch, the full model) and is measured on each task's held-out test "
    "frames. Each section names the commit it was generated at, those its runs were trained at and the machine: "
    "training seconds depend on the machine and on what else ran beside; PSNR does not.",
    "",
)
"""The page's opening lines."""


def command(module: str, arguments: Sequence[Tuple[str, Sequence[str]]]) -> str:
    """The benchmark command that makes one section alone."""
    words = [f"python -m continual_nerf.bench.{module}"]
    for option, values in arguments:
        words.append(f"{option} {shlex.join(values)}")
    return " ".join(words)


@dataclass
class Results:
    """Regenerates docs/results.md and the README's results table from the benchmark modules."""

    jobs: int = 1
    """Runs trained at once, each in a process of its own with cores / jobs threads (unless OMP_NUM_THREADS is set)."""
    device: Device = "cpu"
    """Device every run trains on."""
    data: Path = Path("data/continual-demo")
    """Where the demo scenes are generated (and reused from)."""
    output_dir: Path = Path("outputs/results")
    """The runs; finished ones found here are read back, not trained again."""
    docs: Path = Path("docs/results.md")
    """The page written: its header and the sections regenerated replaced, the others kept."""
    readme: Path = Path("README.md")
    """The README whose table between the results markers is replaced (with the quality section)."""
    sections: Tuple[str, ...] = SECTIONS
    """The sections to measure and rewrite; the page's others are kept as they are."""

    def quality(
        self,
        name: str = "quality",
        settings: Tuple[str, ...] = QUALITY_SETTINGS,
        recipes: Tuple[str, ...] = QUALITY_RECIPES,
        scenes: Tuple[DemoScene, ...] = ("room", "street"),
    ) -> quality.QualityBenchmark:
        return quality.QualityBenchmark(
            scenes=scenes,
            settings=settings,
            recipes=recipes,
            **self.common(name),  # type: ignore[arg-type]
        )

    def real_captures(self) -> Dict[str, real_capture.RealCaptureBenchmark]:
        def bench(scene: str, captures: Tuple[str, ...], features: Tuple[str, ...]):
            return real_capture.RealCaptureBenchmark(
                scenes=(scene,),  # type: ignore[arg-type]
                captures=captures,
                features=features,
                **self.common(f"real-capture-{scene}"),  # type: ignore[arg-type]
            )

        return {
            "room": bench("room", ROOM_CAPTURES, ROOM_FEATURES),
            "street": bench("street", STREET_CAPTURES, STREET_FEATURES),
        }

    def sessions(self) -> sessions.SessionsBenchmark:
        return sessions.SessionsBenchmark(scenes=SESSIONS_SCENES, **self.common("sessions"))  # type: ignore[arg-type]

    def common(self, name: str) -> Dict[str, object]:
        return {"jobs": self.jobs, "device": self.device, "data": self.data, "output_dir": self.output_dir / name}

    def main(self) -> None:
        check_names("sections", self.sections, SECTIONS)
        kept = kept_sections(self.docs, [name for name in SECTIONS if name not in self.sections])
        build = {
            "quality": self.quality_lines,
            "default-budget": self.default_budget_lines,
            "distillation-weight": self.distillation_lines,
            "depth": self.depth_lines,
            "sweep": self.sweep_lines,
            "real-capture": self.capture_lines,
            "sessions": self.sessions_lines,
        }
        lines = list(HEADER)
        for name in SECTIONS:
            lines += build[name]() if name in self.sections else kept[name]
        write_text_atomically(self.docs, "\n".join(lines))
        CONSOLE.print(f"[bold green]Wrote the sections {', '.join(self.sections)} of {self.docs}")
        if "quality" in self.sections:  # its runs are finished: read back, not trained again
            replace_readme_table(self.readme, summary_table(self.quality().measure()))
            CONSOLE.print(f"[bold green]Wrote the results table of {self.readme}")

    def quality_lines(self) -> List[str]:
        return self.grid_lines("quality", self.quality(), BOUNDS_NOTE)

    def default_budget_lines(self) -> List[str]:
        bench = self.quality("default-budget", DEFAULT_BUDGET_SETTINGS, DEFAULT_BUDGET_RECIPES)
        return self.grid_lines("default-budget", bench, DEFAULT_BUDGET_NOTE)

    def distillation_lines(self) -> List[str]:
        bench = self.quality("distillation-weight", DISTILLATION_SETTINGS, DISTILLATION_RECIPES)
        return self.grid_lines("distillation-weight", bench, DISTILLATION_NOTE)

    def grid_lines(self, name: str, bench: quality.QualityBenchmark, note: str) -> List[str]:
        """Section `name`: the tables of a quality grid without a plot, under its command and provenance."""
        results = bench.measure()
        provenance = self.provenance(grid_commits(results.values()))
        return quality_section(bench, results, SECTION_TITLES[name], note, provenance)

    def depth_lines(self) -> List[str]:
        bench = self.quality("depth", DEPTH_SETTINGS, DEPTH_RECIPES)
        results = bench.measure()
        provenance = self.provenance(grid_commits(results.values()))  # before the plot changes the checkout
        quality.plot_quality(with_tasks(results, DEPTH_PLOT_TASKS), self.docs.parent / DEPTH_PLOT)
        lines = quality_section(bench, results, SECTION_TITLES["depth"], DEPTH_NOTE, provenance)
        return [*lines, f"![Final mean PSNR against iterations per task, with and without depth]({DEPTH_PLOT})", ""]

    def sweep_lines(self) -> List[str]:
        bench = self.quality("sweep", SWEEP_SETTINGS, SWEEP_RECIPES, ("long-street",))
        results = bench.measure()
        provenance = self.provenance(grid_commits(results.values()))  # before the plot changes the checkout
        quality.plot_quality(results, self.docs.parent / SWEEP_PLOT)
        lines = quality_section(bench, results, SECTION_TITLES["sweep"], SWEEP_NOTE, provenance)
        return [*lines, f"![Final mean PSNR against the number of tasks on the long street]({SWEEP_PLOT})", ""]

    def capture_lines(self) -> List[str]:
        lines: List[str] = []
        for name, bench in self.real_captures().items():
            results = bench.measure()
            lines += capture_section(name, bench, results, self.provenance(grid_commits([results])))
        return lines

    def sessions_lines(self) -> List[str]:
        bench = self.sessions()
        command_alone = f"{bench.command()} --output-dir outputs/bench-sessions"
        measured = bench.measure()
        provenance = self.provenance(sessions.run_commits(measured))
        return sessions.markdown(command_alone, sessions.results_tables(measured), 2, provenance).splitlines()

    def provenance(self, commits: Iterable[str]) -> str:
        """Where and from what code a section's numbers come."""
        trained = sorted(set(commits))
        runs = f" from runs trained at {', '.join(f'`{c}`' for c in trained)}" if trained else ""
        threads = threads_per_run(self.jobs) or os.environ["OMP_NUM_THREADS"]
        return (
            f"Generated at commit `{source_commit()}`{runs}; {platform.machine()} machine with {os.cpu_count()} cores, "
            f"device {self.device}, torch {torch.__version__}, {self.jobs} run(s) at once, {threads} thread(s) each."
        )


def grid_commits(grids: Iterable[Mapping[str, Mapping[str, RunSummary]]]) -> List[str]:
    """The commits the runs of these grids (setting or capture -> recipe -> run) were trained at."""
    return [run.commit for grid in grids for runs in grid.values() for run in runs.values()]


def kept_sections(page: Path, names: Sequence[str]) -> Dict[str, List[str]]:
    """The lines of each named section of the page as it stands, or a one-line error if the page lacks one."""
    if not names:
        return {}
    if not page.is_file():
        raise SystemExit(f"{page} does not exist: regenerate every section (leave out --sections)")
    blocks: List[List[str]] = []
    for line in page.read_text().splitlines():
        if line.startswith("## ") or not blocks:
            blocks.append([])
        blocks[-1].append(line)
    kept = {}
    for name in names:
        heading = f"## {SECTION_TITLES[name]}"
        lines = [line for block in blocks if block[0].startswith(heading) for line in block]
        if not lines:
            raise SystemExit(f"{page} has no section '{heading}' to keep: regenerate it too (--sections ... {name})")
        kept[name] = lines
    return kept


def with_tasks(results: quality.Results, num_tasks: int) -> quality.Results:
    """The results of the settings with `num_tasks` tasks."""
    return {
        scene: {key: runs for key, runs in by_setting.items() if Setting.parse(key).num_tasks == num_tasks}
        for scene, by_setting in results.items()
    }


def quality_section(
    bench: quality.QualityBenchmark, results: quality.Results, title: str, note: str, provenance: str
) -> List[str]:
    output_dir = f"outputs/{bench.output_dir.name}"
    arguments = [("--scenes", bench.scenes), ("--settings", bench.settings), ("--recipes", bench.recipes)]
    arguments.append(("--output-dir", [output_dir]))
    lines = [f"## {title}", "", f"`{command('quality', arguments)}`", "", provenance, "", note, ""]
    for scene, by_setting in results.items():
        for key, runs in by_setting.items():
            lines += [f"### {scene}, {Setting.parse(key)}", "", *quality.markdown_table(runs), ""]
    return lines


def capture_section(
    name: str, bench: real_capture.RealCaptureBenchmark, results: Dict[str, Dict[str, RunSummary]], provenance: str
) -> List[str]:
    arguments = [("--scenes", bench.scenes), ("--captures", bench.captures), ("--features", bench.features)]
    if bench.options:
        arguments.append(("--options", bench.options))
    run_alone = command("real_capture", [*arguments, ("--output-dir", ["outputs/real-capture"])])
    title = f"{SECTION_TITLES['real-capture']}: {name}, {Setting.parse(bench.setting)}"
    lines = [f"## {title}", "", f"`{run_alone}`", "", provenance, ""]
    for runs in results.values():
        lines += [*real_capture.markdown_table(runs), ""]
    return lines


def summary_table(results: quality.Results) -> str:
    """The README's table: final mean test PSNR of each recipe in each scene and setting."""
    columns = [(scene, key) for scene, by_setting in results.items() for key in by_setting]
    recipes: Mapping[str, RunSummary] = next(iter(next(iter(results.values())).values()))
    head = ["final mean test PSNR (dB)", *(f"{scene}, {key.replace('x', ' x ')}" for scene, key in columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for recipe in recipes:
        cells = [f"{results[scene][key][recipe].final_mean_psnr:.2f}" for scene, key in columns]
        lines.append("| " + " | ".join([recipe, *cells]) + " |")
    return "\n".join(lines)


def replace_readme_table(readme: Path, table: str) -> None:
    """Put `table` between the README's results markers, or say in one line why it cannot."""
    begin, end = map(re.escape, README_MARKERS)
    text = readme.read_text()
    updated, count = re.subn(
        f"{begin}\n.*?{end}", lambda _: f"{README_MARKERS[0]}\n{table}\n{README_MARKERS[1]}", text, flags=re.S
    )
    if count != 1:
        raise SystemExit(f"{readme}: expected one pair of lines {README_MARKERS[0]} / {README_MARKERS[1]}")
    write_text_atomically(readme, updated)


def entrypoint() -> None:
    tyro.cli(Results).main()


if __name__ == "__main__":
    entrypoint()
