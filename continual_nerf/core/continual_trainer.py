"""nerfstudio's Trainer, with the iteration count derived from the task budget, one-line errors for bad input,
atomic checkpoints and a resume (`--load-dir`) that continues a killed run where it stopped. The continual panel in
the viewer is added by the viewer's trainer (continual_nerf/viewer/live_trainer.py), through `extend_viewer`."""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, Literal, Optional, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.external import TCNN_EXISTS
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.utils.writer import EventName
from nerfstudio.viewer.viewer import Viewer

from continual_nerf.atomic_files import describe, os_error_of, remove_stale_partials
from continual_nerf.checkpoints import (
    check_method,
    check_resumable,
    checkpoint_steps,
    find_checkpoint,
    read_checkpoint,
    restore_rng_states,
    rng_states,
    save_checkpoint_file,
    slim_checkpoint,
)
from continual_nerf.compilation import warm_up
from continual_nerf.core import distributed
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_pipeline import (
    CONTINUE_OPTION,
    ORACLE_PREFIX,
    ContinualPipeline,
    ContinualPipelineConfig,
)
from continual_nerf.core.sessions import (
    SESSIONS_FILENAME,
    checkpoint_record,
    grow_optimizer_state,
    same_capture,
    task_checkpoints,
)
from continual_nerf.errors import CheckpointError, ContinualConfigError, ContinualNerfError, OutputError, first_line
from continual_nerf.interrupts import EXIT_CODES, INTERRUPTS, resume_command
from continual_nerf.nerfstudio_compat import (
    DeferredPauseTrainer,
    count_progress_to,
    first_step,
    forget_empty_profile,
    launch_processes_here,
    leave_pause,
    quiet_nerfstudio_warnings,
    set_resume_step,
    stop_rendering_at_exit,
    viewer_answering_when_ready,
)
from continual_nerf.run_lock import claim_run_folder, release_run_folder
from continual_nerf.validated_config import ValidatedConfig

UNBOUNDED_ITERATIONS = 10**9
"""Iterations nerfstudio's loop is given when the tasks, not a count, end the run (timed or streamed tasks)."""


@dataclass
class ContinualTrainerConfig(ValidatedConfig, TrainerConfig):
    """TrainerConfig whose max_num_iterations follows from num_tasks x the per-task budget unless it is given."""

    _target: Type = field(default_factory=lambda: ContinualTrainer)
    pipeline: ContinualPipelineConfig = field(default_factory=ContinualPipelineConfig)
    """The continual pipeline: the task split, its datamanager, the model and the replay oracle."""
    max_num_iterations: Optional[int] = None  # type: ignore[assignment]
    """Cap on the run's training iterations; None: the task budget decides (num_tasks x iterations_per_task)."""
    deterministic: bool = False
    """Use torch's deterministic algorithms: a seed gives bit-identical losses on CPU, at up to twice the step time."""

    def validate(self) -> None:
        super().validate()
        if self.max_num_iterations is not None and self.max_num_iterations < 1:
            raise ContinualConfigError(f"--max-num-iterations must be at least 1, got {self.max_num_iterations}")
        if self.pipeline.continue_with_new_capture and self.load_dir is None and self.load_checkpoint is None:
            raise ContinualConfigError(
                "--pipeline.continue-with-new-capture needs the run to continue: --load-dir <run>/nerfstudio_models"
            )
        if self.start_paused and self.several_processes:
            # the other processes would wait for rank 0's first step in a collective that times out
            raise ContinualConfigError("--start-paused needs one process: pause from the viewer once training runs")
        if self.machine.device_type == "cuda" and not torch.cuda.is_available():
            # as nerfstudio, no silent change of device: a CPU run of the default budget takes hours, not minutes
            raise ContinualConfigError(
                "--machine.device-type cuda (the default): torch finds no CUDA GPU here; add --machine.device-type cpu "
                "to train on the CPU"
            )

    @property
    def several_processes(self) -> bool:
        """Whether ns-train starts more than one process (--machine.num-devices x --machine.num-machines)."""
        return self.machine.num_devices * self.machine.num_machines > 1

    def setup(self, **kwargs: Any) -> Any:
        INTERRUPTS.install()  # Ctrl-C while nerfstudio's Trainer starts: no traceback either
        try:
            with one_line_exit(self.method_name):
                return super().setup(**kwargs)
        finally:
            INTERRUPTS.restore()

    def print_to_terminal(self) -> None:
        """What the run does and where it writes, in two lines: nerfstudio's dump of every option (~250 lines) stays in
        the run folder's config.yml.

        ns-train calls this first, before it saves the config and starts training: from here to the end of the
        process Ctrl-C ends the run with one line, never a traceback.
        """
        INTERRUPTS.install()
        datamanager = self.pipeline.datamanager
        processes = self.machine.num_devices * self.machine.num_machines
        device = self.machine.device_type + (f" x {processes} processes" if processes > 1 else "")
        stops = "" if self.max_num_iterations is None else f", at most {self.max_num_iterations} iterations"
        folder = datamanager.data or getattr(
            datamanager.dataparser, "data", None
        )  # ns-train's --data, else the parser's
        data = ", ".join(str(part) for part in (dataparser_name(datamanager.dataparser), folder) if part)
        for line in (
            f"{self.method_name}: {datamanager.describe_tasks()}{stops} on {device}; data: {data}",
            f"Run folder: {self.get_base_dir()} (config.yml there holds every option)",
        ):
            CONSOLE.print(line, markup=False, soft_wrap=True)

    def resume_source(self) -> Optional[Path]:
        """The run folder this run resumes (or continues) from, if any."""
        if self.load_dir is not None:
            return self.load_dir.parent
        return None if self.load_checkpoint is None else self.load_checkpoint.parent.parent

    def checkpoint_to_load(self) -> Optional[Path]:
        """The checkpoint --load-dir (its latest, or --load-step's) or --load-checkpoint names, if any."""
        if self.load_dir is not None:
            return find_checkpoint(self.load_dir, self.load_step)
        return self.load_checkpoint

    def record_earlier_sessions(self, base_dir: Path) -> None:
        """A run that continues earlier sessions (a new capture, or resuming a continued run) writes their record from
        the checkpoint into its run folder, for its datamanager to read whenever the run is set up (ns-eval, ...)."""
        try:
            path = self.checkpoint_to_load()
        except CheckpointError:
            return  # nothing to load: the trainer's set-up says so in one line
        if path is None:
            return
        state = read_checkpoint(path)
        record = checkpoint_record(state, path)
        if self.pipeline.continue_with_new_capture:
            if record is None:
                raise CheckpointError(f"{path}: written before runs recorded their sessions; it cannot be continued")
            earlier = dataclasses.replace(
                record, next_step=int(state["step"]) + 1, task_checkpoints=task_checkpoints(record, state, path)
            )
        elif record is not None and len(record.tasks_per_session) > 1:
            earlier = record.first_sessions(len(record.tasks_per_session) - 1)
        else:
            return  # a first session resumes from its own capture
        file = base_dir / SESSIONS_FILENAME
        earlier.save(file)
        self.pipeline.datamanager.earlier_sessions = file

    def save_config(self) -> None:
        """Claim the run folder for the run's life, then write nerfstudio's config.yml there, unless the folder holds
        another run's results (they would be overwritten); temporary files of killed saves are removed.

        `ns-train` calls this just before it starts its processes: with several, they go through the plugin's worker
        (CPU processes, one-line errors), and the run folder is machine 0's alone (process 0 writes it).
        """
        quiet_nerfstudio_warnings(on_cpu=self.machine.device_type == "cpu")  # and in the processes ns-train starts
        with one_line_exit(self.method_name):
            self.validate()  # before the run folder is made: a run that cannot start leaves nothing behind
        if self.several_processes:
            launch_processes_here(self.mark_failed)
        if self.machine.machine_rank > 0:
            return
        base_dir, source = self.get_base_dir(), self.resume_source()
        with one_line_exit(self.method_name):
            previous = claim_run_folder(base_dir)
            if previous is not None:
                CONSOLE.print(
                    f"{base_dir}: process {previous}, which held it, is no longer running", markup=False, soft_wrap=True
                )
            # a later session is a run of its own: it never writes into the folder of the run it continues
            continues_itself = None if self.pipeline.continue_with_new_capture else source
            if self._holds_another_run(base_dir, continues_itself):
                release_run_folder(base_dir)
                raise ContinualConfigError(
                    f"{base_dir} already holds a run; choose another --timestamp or --experiment-name, or continue "
                    f"that run with --load-dir {self.get_checkpoint_dir()}"
                )
            self.record_earlier_sessions(base_dir)
            super().save_config()
        for folder in (base_dir, source):
            for stale in remove_stale_partials(folder) if folder is not None else []:
                CONSOLE.print(f"Removed {stale}, left by a save that was killed", markup=False, soft_wrap=True)

    def mark_failed(self) -> None:
        """Say in the run folder that the run ended by an error when a process died without saying so (killed)."""
        path = self.get_base_dir() / ACCURACY_MATRIX_FILENAME
        if self.machine.machine_rank > 0 or not path.is_file():
            return
        accuracy = AccuracyMatrix.read(path)
        if accuracy.status == "training":
            accuracy.status = "failed"
            with contextlib.suppress(OutputError):  # a full disk may refuse this too: the error is what matters
                accuracy.write(self.get_base_dir())

    def _holds_another_run(self, base_dir: Path, source: Optional[Path]) -> bool:
        """Whether `base_dir` holds results of a run this one does not continue."""
        holds_a_run = (base_dir / ACCURACY_MATRIX_FILENAME).exists() or (
            self.get_checkpoint_dir().is_dir() and bool(checkpoint_steps(self.get_checkpoint_dir()))
        )
        return holds_a_run and not (source is not None and source.resolve() == base_dir.resolve())


def dataparser_name(dataparser: Any) -> str:
    """The name `ns-train` knows a dataparser by (continual-demo, ...)."""
    from nerfstudio.configs.dataparser_configs import all_dataparsers  # discovers the plugins, this one among them

    names = [name for name, config in all_dataparsers.items() if type(config) is type(dataparser)]
    return names[0] if names else type(dataparser).__name__


@contextlib.contextmanager
def one_line_exit(method_name: Optional[str]) -> Iterator[None]:
    """End the process with one line for bad input (an option, a dataset file, an image of a task released mid-run)
    or a file it cannot write, nerfstudio's own included; anything else keeps its traceback, which is worth seeing."""
    try:
        yield
    except Exception as error:
        cause = os_error_of(error)
        if isinstance(error, ContinualNerfError):
            line = str(error)
        elif cause is not None and cause.filename is not None:
            line = f"{cause.filename}: {describe(cause)}"
        else:
            raise
        raise SystemExit(f"{method_name}: error: {line}") from None


class ContinualTrainer(DeferredPauseTrainer):
    """Runs nerfstudio's training loop unchanged; the pipeline's callbacks switch tasks and stop it."""

    config: ContinualTrainerConfig
    pipeline: ContinualPipeline

    def __init__(self, config: ContinualTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        quiet_nerfstudio_warnings(on_cpu=config.machine.device_type == "cpu")
        if not distributed.is_main():
            CONSOLE.quiet = True  # every process would print the same lines: rank 0 speaks for the run
        super().__init__(config, local_rank, world_size)
        self._resumed_from: Optional[Path] = None
        """The checkpoint folder this run resumed from, if any."""
        self._last_trained_step: Optional[int] = None
        """The last step this process trained, once one is."""
        self._saved_step: Optional[int] = None
        """The step of the last checkpoint this process saved."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        INTERRUPTS.install()  # Ctrl-C while setting up (waiting for a capture's first task, ...): no traceback
        try:
            self._set_up(test_mode)
        except BaseException:
            forget_empty_profile()  # ended before training: nothing to report but why it ended
            raise
        finally:
            INTERRUPTS.restore()  # train() installs them again: a trainer only set up leaves no handler behind
        location = TrainingCallbackLocation
        self.callbacks += [
            TrainingCallback([location.BEFORE_TRAIN_ITERATION], self._answer_interrupt),
            TrainingCallback([location.AFTER_TRAIN_ITERATION], self._count_trained_step),
            TrainingCallback([location.AFTER_TRAIN], self._after_last_step),
        ]
        if distributed.is_distributed():  # after the panel's: a pause it starts at a task's end holds every rank
            self.callbacks.append(
                TrainingCallback(
                    [location.AFTER_TRAIN_ITERATION], distributed.hold_while_paused, args=[self, self.pause_now]
                )
            )

    def _set_up(self, test_mode: Literal["test", "val", "inference"]) -> None:
        self._use_torch_without_tiny_cuda_nn()
        self.config.max_num_iterations = self._iterations_to_run()
        if self.config.max_num_iterations == UNBOUNDED_ITERATIONS:  # no end known: an ETA would count to the cap
            writer_config = self.config.logging.local_writer
            writer_config.stats_to_track = tuple(s for s in writer_config.stats_to_track if s != EventName.ETA)
        if self.config.deterministic:
            # the hash grid's gradients are scatter-adds run in parallel: their summation order varies the last bits
            torch.use_deterministic_algorithms(True, warn_only=True)
        with viewer_answering_when_ready():  # the page answers once it shows what extend_viewer adds
            with one_line_exit(self.config.method_name):
                super().setup(test_mode)
            # a resumed run's loop counts its iterations from the resumed step: % done and ETA count to the run's end
            count_progress_to(first_step(self) + self.config.max_num_iterations)
            if isinstance(self.viewer_state, Viewer) and not distributed.is_main():
                # nerfstudio starts a viewer in the first process of every machine; rank 0's alone is fed and obeyed
                self.viewer_state.viser_server.stop()
                self.viewer_state = None
            if isinstance(self.viewer_state, Viewer):
                self.extend_viewer(self.viewer_state)
        warm_up(
            self.pipeline.model,
            self.config.pipeline.datamanager.train_num_rays_per_batch,
            progress=lambda part: self.show_stage(f"compiling the model (torch.compile), {part}"),
        )
        self.show_stage(f"reading task {self.pipeline.task.current + 1}'s images")

    def _use_torch_without_tiny_cuda_nn(self) -> None:
        """Build the model's hash grids and MLPs in torch when tiny-cuda-nn is not installed, as nerfstudio falls back
        to, without its warning block per module and model (twelve in a run: the replay oracle is a second model);
        on a GPU, one line says what installing it would bring."""
        model = self.config.pipeline.model
        if getattr(model, "implementation", None) != "tcnn" or TCNN_EXISTS:
            return
        if self.device.startswith("cuda") and distributed.is_main():
            CONSOLE.print(
                "tiny-cuda-nn is not installed: the hash grids and MLPs run in torch (pip install "
                "git+https://github.com/NVlabs/tiny-cuda-nn/#subdirectory=bindings/torch for its fused kernels)",
                markup=False,
                soft_wrap=True,
            )
        model.implementation = "torch"  # type: ignore[attr-defined]

    def extend_viewer(self, viewer: Viewer) -> None:
        """Add to nerfstudio's viewer before its page first answers (the viewer's trainer adds the continual panel)."""

    def show_stage(self, stage: str) -> None:
        """Say what set-up is doing before training starts (the viewer's trainer shows it in its panel)."""

    def pause_waits(self) -> bool:
        # with several processes a pause (the viewer's button, from its own thread) starts at the end of an
        # iteration, where every process learns of it (hold_while_paused); nerfstudio's loop, seeing it sooner, would
        # stop process 0 alone while the others wait in the next gradient all-reduce
        return distributed.is_distributed()

    def _check_viewer_warnings(self) -> None:
        if isinstance(self.viewer_state, Viewer):  # nerfstudio calls this right after the viewer starts
            stop_rendering_at_exit(self.viewer_state)
        # nerfstudio's note says no evaluation runs with the viewer alone: its periodic evaluation does not, but the
        # accuracy matrix is measured at the end of every task whatever --vis says
        if self.config.is_viewer_enabled() and not self.config.is_tensorboard_enabled():
            CONSOLE.print(
                "[NOTE] The test PSNR of every task is measured at the end of each task (viewer panel, "
                "accuracy_matrix.json); --vis viewer+tensorboard also logs the losses and nerfstudio's periodic "
                "evaluation."
            )

    def _iterations_to_run(self) -> int:
        """The task budget's iterations (a generous cap when tasks are timed or streamed), or --max-num-iterations."""
        budgeted = self.config.pipeline.datamanager.budgeted_iterations()
        cap = self.config.max_num_iterations
        if cap is None:
            return budgeted if budgeted is not None else UNBOUNDED_ITERATIONS
        if budgeted is None or cap < budgeted:
            tasks_take = "" if budgeted is None else f" (its tasks take {budgeted})"
            CONSOLE.print(f"[bold yellow]--max-num-iterations {cap} may end the run before its last task{tasks_take}")
        return cap

    def train(self) -> None:
        INTERRUPTS.install()
        # a signal while the viewer has paused training: the next iteration must come, to answer it
        INTERRUPTS.deferring, INTERRUPTS.on_signal = True, lambda: leave_pause(self)
        try:
            with one_line_exit(self.config.method_name):
                self._train_saying_so_if_it_fails()
        finally:
            INTERRUPTS.restore()
            release_run_folder(self.base_dir)
            forget_empty_profile()

    def _answer_interrupt(self, step: int) -> None:
        """If a signal came during the last iteration: checkpoint that step, mark the run interrupted, say how to
        resume it and exit with 128 + the signal."""
        # several processes stop at the same step, the one rank 0 received its signal before
        number = distributed.decided_by_main(INTERRUPTS.received or 0, self.pipeline.device)
        if not number:
            return
        if not distributed.is_main():
            # rank 0 saves, writes and says how to resume; the launcher stops every process once one has ended
            distributed.barrier()
            raise SystemExit(EXIT_CODES[number])
        if step > first_step(self):
            self.save_checkpoint(step - 1)
            # this run's own checkpoint resumes it, a continued run's too: without starting another session
            command = resume_command(self.checkpoint_dir, sys.argv, dropped=[CONTINUE_OPTION])
            how = f"step {step - 1} saved; resume with: {command}"
        elif self._resumed_from is not None:
            how = f"no step trained since resuming; resume with: {resume_command(self._resumed_from, sys.argv)}"
        else:
            how = "no step trained yet, nothing to resume"
        self.pipeline.accuracy.status = "interrupted"
        self.pipeline.accuracy.write(self.base_dir)
        print(
            f"{self.config.method_name}: interrupted by {signal.Signals(number).name}: {how}",
            file=sys.stderr,
            flush=True,
        )
        INTERRUPTS.answered = True
        distributed.barrier()
        raise SystemExit(EXIT_CODES[number])

    def _count_trained_step(self, step: int) -> None:
        self._last_trained_step = step

    def _after_train(self) -> None:
        # when the pipeline stops the loop (the last task done before --max-num-iterations, or a capture's end), the
        # loop has moved `step` on to a step it never trains: the final checkpoint and the step shown are the last one
        # trained
        trained = self._last_trained_step
        self.step = trained if trained is not None else first_step(self) - 1
        super()._after_train()

    def _after_last_step(self, step: int) -> None:
        """Training is over and saved: from now on a signal (the viewer may stay open) ends the process at once."""
        INTERRUPTS.deferring = False
        if INTERRUPTS.received is not None:
            print(f"{self.config.method_name}: interrupted after its last step; the run is complete", file=sys.stderr)
            raise SystemExit(EXIT_CODES[INTERRUPTS.received])

    def _train_saying_so_if_it_fails(self) -> None:
        accuracy = self.pipeline.accuracy
        main = distributed.is_main()  # rank 0 alone writes results
        try:
            if main:
                accuracy.write(self.base_dir)  # the run folder says "not finished" from the start, however it ends
            super().train()
        except Exception:
            if main and not accuracy.finished:
                accuracy.status = "failed"
                with contextlib.suppress(OutputError):  # a full disk may refuse this too: the error is what matters
                    accuracy.write(self.base_dir)
            raise

    def _load_checkpoint(self) -> None:
        """Resume from --load-dir (latest or --load-step) or --load-checkpoint: nerfstudio's states plus the RNGs; or,
        with --pipeline.continue-with-new-capture, go on from there on a new capture."""
        first_step_of_session = self.pipeline.datamanager.session_first_step
        if self.config.max_num_iterations != UNBOUNDED_ITERATIONS:  # the earlier sessions' steps come first
            assert self.config.max_num_iterations is not None, "setup() sets it before loading"
            self.config.max_num_iterations += first_step_of_session
        path = self.config.checkpoint_to_load()
        if path is None:
            return super()._load_checkpoint()
        state = read_checkpoint(path)
        self._resumed_from = path.parent
        check_method(state, path, self.config.method_name)
        if self.config.pipeline.continue_with_new_capture:
            return self._continue_on_new_capture(state, path)
        self._load_states(state, path)
        pipeline = self.pipeline
        accuracy = pipeline.accuracy
        if accuracy.finished:
            raise CheckpointError(
                f"{path}: its run already trained all {accuracy.num_tasks} tasks (to go on learning a later capture, "
                "add --pipeline.continue-with-new-capture True)"
            )
        self._check_budget_reaches(state["step"], path)
        check_resumable(state, path, find_checkpoint(path.parent, None))
        if distributed.is_main():  # the other ranks keep their own seeds (--machine.seed + rank): their rays differ
            restore_rng_states(state["rng"])
        set_resume_step(self, state["step"] + 1)
        CONSOLE.print(
            f"Resuming from {path} at step {first_step(self)}: task {pipeline.task.current + 1}/"
            f"{pipeline.known_tasks}, {pipeline.budget.iterations_done} iterations into it"
        )

    def _continue_on_new_capture(self, state: Dict[str, Any], path: Path) -> None:
        """Start this capture's tasks after the checkpoint's: its model, optimizers (their moments from zero with
        --pipeline.restart-optimizer-moments) and random generators go on as if the captures were one, the model the
        replay oracle of every earlier task."""
        pipeline, datamanager = self.pipeline, self.pipeline.datamanager
        check_resumable(state, path, find_checkpoint(path.parent, None))  # a closed task's weights alone go on no run
        record = checkpoint_record(state, path)
        assert record is not None, "record_earlier_sessions read it"
        if same_capture(record, datamanager.train_dataparser_outputs.image_filenames[record.num_frames :]):
            raise CheckpointError(
                f"{path}: its last session was trained on {datamanager.capture_name()}: a later session needs a later "
                "capture (to resume an unfinished run, leave --pipeline.continue-with-new-capture out)"
            )
        initial_sampler = self._initial_sampler()
        try:
            pipeline.continue_session(state["pipeline"], state["step"])
            for name, optimizer in self.optimizers.optimizers.items():
                optimizer.load_state_dict(grow_optimizer_state(state["optimizers"][name], optimizer))
            if initial_sampler is not None:
                self._restart_sampler(initial_sampler)
            if self.config.pipeline.restart_optimizer_moments:
                for optimizer in self.optimizers.optimizers.values():
                    optimizer.state.clear()
            if self.config.load_scheduler:
                self.optimizers.load_schedulers(state.get("schedulers", {}))
            self.grad_scaler.load_state_dict(state["scalers"])
        except ContinualNerfError as error:
            raise CheckpointError(f"{path}: {error}") from None
        except (RuntimeError, KeyError, ValueError) as error:
            raise CheckpointError(
                f"{path}: does not fit this run ({first_line(error)}); continue with the options it was trained with"
            ) from None
        if distributed.is_main():
            restore_rng_states(state["rng"])
        set_resume_step(self, state["step"] + 1)
        earlier = datamanager.earlier_tasks
        CONSOLE.print(
            f"Continuing {path} (tasks 1-{earlier}) on {datamanager.capture_name()}: tasks {earlier + 1}-"
            f"{pipeline.known_tasks} from step {first_step(self)}",
            markup=False,
            soft_wrap=True,
        )

    def _initial_sampler(self) -> Optional[Dict[str, torch.Tensor]]:
        """The proposal networks' weights as the model was built, before a checkpoint is loaded into it, if a later
        session relearns them (--pipeline.relearn-proposal-networks; models without them: None)."""
        networks = getattr(self.pipeline.model, "proposal_networks", None)
        if not self.config.pipeline.relearn_proposal_networks or networks is None:
            return None
        return {key: value.clone() for key, value in networks.state_dict().items()}

    def _restart_sampler(self, initial: Dict[str, torch.Tensor]) -> None:
        """The proposal networks back at their initial weights, their optimizer moments dropped (the replay oracle,
        frozen from the loaded model, keeps the loaded ones)."""
        networks: torch.nn.Module = getattr(self.pipeline.model, "proposal_networks")
        networks.load_state_dict(initial)
        for optimizer in self.optimizers.optimizers.values():
            for parameter in networks.parameters():
                optimizer.state.pop(parameter, None)

    def _check_budget_reaches(self, step: int, path: Path) -> None:
        """Refuse a checkpoint at or past the last step this run has: nerfstudio's loop would not run at all."""
        total = self.config.max_num_iterations
        assert total is not None, "setup() sets it before loading"
        if step + 1 < total:
            return
        datamanager = self.config.pipeline.datamanager
        raise CheckpointError(
            f"{path}: is at step {step}, beyond the {total} iterations this run has (--pipeline.datamanager."
            f"iterations-per-task {datamanager.iterations_per_task} for {datamanager.num_tasks} tasks, or "
            "--max-num-iterations); resume with the options it was trained with"
        )

    def _load_states(self, state: Dict[str, Any], path: Path) -> None:
        """Load pipeline (model, oracle, task progress, accuracy matrix), optimizers, schedulers and grad scaler."""
        try:
            self.pipeline.load_pipeline(state["pipeline"], state["step"])
            self.optimizers.load_optimizers(state["optimizers"])
            if self.config.load_scheduler:
                self.optimizers.load_schedulers(state.get("schedulers", {}))
            self.grad_scaler.load_state_dict(state["scalers"])
        except ContinualNerfError as error:
            raise CheckpointError(f"{path}: {error}") from None
        except (RuntimeError, KeyError, ValueError) as error:
            raise CheckpointError(
                f"{path}: does not fit this run ({first_line(error)}); resume with the options it was trained with"
            ) from None

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint (file name and keys) plus the RNG states, renamed into place once complete. The one
        saved before it keeps the model's weights alone if its step ended a task (the run viewer's task slider and
        ns-eval read those), and goes if it did not: only the latest is needed to resume."""
        if step == self._saved_step or step < first_step(self):
            return  # saved at its task's end already, or no step trained since the run started or resumed
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        save_checkpoint_file(self.checkpoint_state(step), path)
        if self.config.save_only_latest_checkpoint:
            for older in checkpoint_steps(self.checkpoint_dir).values():
                if older != path:
                    older.unlink()
        elif self._saved_step is not None:
            self._keep_weights_only(self._saved_step)
        self._saved_step = step

    def _keep_weights_only(self, step: int) -> None:
        """The checkpoint of `step`, superseded: weights only where a task ended there, removed elsewhere."""
        older = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        if not older.exists():
            return
        if step in self.pipeline.accuracy.steps:
            slim_checkpoint(older, ORACLE_PREFIX)
        else:
            older.unlink()

    def checkpoint_state(self, step: int) -> Dict[str, Any]:
        return {
            "step": step,
            "method": self.config.method_name,
            "pipeline": self.pipeline.checkpoint_state_dict(),
            "optimizers": {name: optimizer.state_dict() for name, optimizer in self.optimizers.optimizers.items()},
            "schedulers": {name: scheduler.state_dict() for name, scheduler in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            "rng": rng_states(),
        }
