"""What every command shares: the typer app, ``--version``, the one-line error with exit status 2,
robots, the options several commands take, and progress display."""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path
from typing import Iterator, List, Optional

import typer

from .._version import __version__
from ..errors import InputError
from .helptext import App, setting_option

app = App(add_completion=False, no_args_is_help=True,
                  help="Multimodal GP inverse dynamics from messy robot logs.")


EXIT_BAD_INPUT = 2


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"mmgp {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Multimodal GP inverse dynamics from messy robot logs."""


def _fail(exc: Exception) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def echo_warnings(warnings) -> None:
    """Each warning of a command (the log checks of ``mmgp.physics.plausibility`` first) on its
    own stderr line, ``warning: ...``: train, diagnose and compare print them alike."""
    for line in warnings or []:
        typer.echo(f"warning: {line}", err=True)


def read_logs(logs) -> list:
    """Each of ``logs`` read and checked once (:func:`mmgp.data.logs.read_log`, a RobotLog that
    the command passes on: the robot is found in its metadata, the rows are not read again).
    Before a command loads torch, scikit-learn or Pinocchio (seconds), so a wrong path, file type
    or column answers at once (the header is checked before the rows); exit status 2."""
    from ..data.logs import read_log

    try:
        return [read_log(log) for log in logs]
    except InputError as exc:
        _fail(exc)


DEVICE_HELP = "torch device of the GPs: cpu (default), cuda, cuda:N or auto (cuda when there is one)."


def device_option(section: str | None = None, help: str = DEVICE_HELP) -> Optional[str]:
    """``--device``; with ``section``, a setting of it (help shows the shipped default)."""
    if section is None:
        return typer.Option(None, "--device", help=help)
    return setting_option(section, "device", "--device", help=help.replace("cpu (default)", "cpu"))


def _check_device(device: Optional[str]) -> None:
    from ..gp.linalg import resolve_device

    if device is None:
        return
    try:
        resolve_device(device)
    except (ValueError, RuntimeError) as exc:
        raise InputError(f"--device {device}: {exc}") from None


def _stop_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def command_numerics(device: Optional[str] = None) -> Iterator[None]:
    """What every command computes under: the one thread policy (:mod:`mmgp.threads`: one thread,
    large factorisations on idle cores), ``device`` as the default device of every GP built
    inside (:func:`mmgp.gp.linalg.default_device`), and SIGTERM (``timeout``, schedulers) turned
    into an ordinary exit, so an interrupted command removes its unfinished output folder."""
    from ..gp.linalg import default_device
    from ..threads import limit_threads

    _check_device(device)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _stop_on_sigterm) if in_main else None
    try:
        with default_device(device), limit_threads(1):
            yield
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


def _given(*paths) -> list[Path]:
    """The input paths a command was given (options left out are None), for the writers'
    ``inputs=``: an output may never be, contain or lie inside one of them."""
    return [Path(p) for p in paths if p is not None]


def _model_files(model_dir: Path) -> list[Path]:
    """The files of a saved model (the folder itself may also hold outputs, e.g. evaluation.json)."""
    return [Path(model_dir) / "model.json", Path(model_dir) / "model.npz"]


def _robot_for(log_path, robot: Optional[str], urdf: Optional[Path], n_joints: Optional[int] = None):
    from ..physics.robot import load_robot

    return load_robot(robot=robot, urdf=urdf, log_path=log_path, n_joints=n_joints)


def parameter_default(func, name: str):
    """The default of parameter ``name`` of ``func`` (what the library does when the CLI passes nothing)."""
    import inspect

    return inspect.signature(func).parameters[name].default


# Options several commands take, with one help text each.

def out_dir_option() -> Path:
    return typer.Option(..., "--out", help="Output folder (created; refused if non-empty).")


def logs_argument(help: str = "One or more logs (Parquet or CSV).") -> List[Path]:
    return typer.Argument(..., help=help)


def config_option(section: str, more: str = "") -> Optional[Path]:
    return typer.Option(None, "--config", help=f"YAML settings file, section '{section}'{more}.")


def force_option(what: str = "--out") -> bool:
    return typer.Option(False, "--force", help=f"Replace an existing {what}.")


def quiet_option() -> bool:
    return typer.Option(False, "--quiet", help="No progress output.")


def robot_option() -> Optional[str]:
    return typer.Option(None, "--robot", help="example-robot-data robot name (e.g. panda); default: "
                                              "the one the log's metadata names.")


def urdf_option() -> Optional[Path]:
    return typer.Option(None, "--urdf", help="URDF file of the robot (instead of --robot).")


def seed_option(default: Optional[int] = None, section: str | None = None) -> Optional[int]:
    """``--seed``; with ``section``, a setting of it (None unless given, help shows the shipped default)."""
    if section is not None:
        return setting_option(section, "seed", "--seed", help="Random seed (same seed, same result).")
    return typer.Option(default, "--seed", help="Random seed (same seed, same result).")


def thinning_line(n_used: int, n_read: int, setting: str) -> str | None:
    """The line a command prints when it used fewer samples than it read, e.g.
    "2,100 of 20,544 samples used: rate_hz 100"; None when it used them all."""
    return f"{n_used:,} of {n_read:,} samples used: {setting}" if n_used < n_read else None


#: seconds without a line after which a piped display says what it is still doing
HEARTBEAT_S = 5.0
HEARTBEAT_ENV = "MMGP_HEARTBEAT_S"


def heartbeat_seconds() -> float:
    """The heartbeat interval: ``MMGP_HEARTBEAT_S`` when set to a positive number, else 5 s."""
    try:
        value = float(os.environ.get(HEARTBEAT_ENV, ""))
    except ValueError:
        return HEARTBEAT_S
    return value if value > 0 else HEARTBEAT_S


class ProgressDisplay:
    """Progress of long work on stderr; nothing at all when ``quiet``. On a terminal: a bar per
    stage with done/total, elapsed time and ETA (rich), the stage's lines above it (from the
    start: never an empty line). Otherwise (a pipe, a log file): the lines alone, each after the
    clock time and the seconds since the command started, and a heartbeat: after ``heartbeat_s``
    (default :func:`heartbeat_seconds`) without a line, "still <what runs now> (N s)".

    While open it listens to the library's stage reports (:mod:`mmgp.progress`): each is a line
    and what runs now. Use as a context manager; :meth:`stage` starts a bar (``follow``: its count
    follows the library's reports of that work, e.g. "diagnosis"), :meth:`step` reports a step."""

    def __init__(self, quiet: bool = False, console=None, heartbeat_s: float | None = None):
        self.quiet = quiet
        self._console = console
        self._bar = None
        self._task = None
        self._follow = self._follow_total = None
        self._placeholder = False
        self.heartbeat_s = heartbeat_s if heartbeat_s is not None else heartbeat_seconds()
        self._lock = threading.RLock()
        self._t0 = self._last = self._since = time.monotonic()
        self._what = "starting"
        self._stop = threading.Event()
        self._exits = contextlib.ExitStack()

    def __enter__(self) -> "ProgressDisplay":
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        from ..progress import listening

        console = self._console = self._console or Console(stderr=True)
        if self.quiet:
            return self
        if console.is_terminal:
            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console)
            self._bar.start()
            self._task = self._bar.add_task("starting", total=None)
            self._placeholder = True  # no empty line before the first stage; replaced by it
        else:
            beat = threading.Thread(target=self._heartbeat, name="mmgp-heartbeat", daemon=True)
            beat.start()
            self._exits.callback(beat.join)
            self._exits.callback(self._stop.set)
        self._exits.enter_context(listening(self._report))
        return self

    def __exit__(self, *exc) -> None:
        self._exits.close()
        if self._bar is not None:
            self._finish_stage()
            self._bar.stop()
            self._bar = None

    @property
    def live(self) -> bool:
        """Whether a bar is shown (a terminal, not quiet)."""
        return self._bar is not None

    def _finish_stage(self) -> None:
        # A stage that ends early (EM converged before its sweep limit) shows as complete.
        if self._task is not None:
            done = max(self._current().completed, 1)
            self._bar.update(self._task, total=done, completed=done)

    def _current(self):
        return next(t for t in self._bar.tasks if t.id == self._task)

    def _print(self, line: str) -> None:
        """``line`` above the bar, or on its own with the time prefix (under the lock)."""
        with self._lock:
            now = time.monotonic()
            self._last = now
            if self._bar is not None:
                self._bar.console.print(line, markup=False, highlight=False, emoji=False)
            else:
                stamp = f"{time.strftime('%H:%M:%S')} {now - self._t0:6.1f}s "
                self._console.print(stamp + line, markup=False, highlight=False, emoji=False, soft_wrap=True)

    def _heartbeat(self) -> None:
        while not self._stop.wait(min(1.0, self.heartbeat_s / 5)):
            with self._lock:
                now = time.monotonic()
                if now - self._last >= self.heartbeat_s:
                    self._print(f"  still {self._what} ({now - self._since:.0f} s)")

    def _report(self, message: str, *, work: str = "", done: int | None = None, total: int | None = None) -> None:
        """A stage report of the library (:func:`mmgp.progress.report`): a line, and what runs now."""
        with self._lock:
            self._what, self._since = message, time.monotonic()
            if self._follow and work == self._follow and done is not None:
                of = self._current().total if self._bar is not None else self._follow_total
                self.step(f"{message} [{done + 1}/{of or total}]", completed=done)
            else:
                self.step(message)

    def waiting(self, what: str) -> None:
        """Say what runs now without a line of its own: the bar's text on a terminal, the
        heartbeat's "still <what>" when piped (a quick failure after it stays one error line)."""
        if self.quiet:
            return
        with self._lock:
            self._what, self._since = what, time.monotonic()
            if self._bar is not None and self._task is not None:
                self._bar.update(self._task, description=what)

    def stage(self, description: str, total: int | None, follow: str | None = None, line: bool = True) -> None:
        """Start a bar for ``total`` steps (None: unknown, no ETA); the previous one is completed.
        ``follow``: the library's reports of this work set the count done. Piped, the stage is a
        line of its own unless ``line`` is False (then the heartbeat names it)."""
        if self.quiet:
            return
        with self._lock:
            self._what, self._since = description, time.monotonic()
            self._follow, self._follow_total = follow, total
            if self._bar is not None:
                if self._placeholder:
                    self._bar.remove_task(self._task)
                    self._placeholder = False
                else:
                    self._finish_stage()
                self._task = self._bar.add_task(description, total=total)
            elif line:
                self._print(description + (f" ({total} steps)" if total else ""))

    def step(self, line: str | None = None, *, completed: int | None = None, advance: int = 0,
             total: int | None = None) -> None:
        """Report a step: print ``line`` (above the bar on a terminal), then set the bar to
        ``completed`` steps or move it on by ``advance`` (and its length to ``total``, once known)."""
        if self.quiet:
            return
        with self._lock:
            if line is not None:
                self._print(line)
            if self._bar is None or self._task is None:
                return
            total = total if total is not None else self._current().total
            if completed is not None and total is not None and completed > total:
                total = completed  # a limit that was an estimate
            self._bar.update(self._task, total=total, completed=completed, advance=advance or None)


def sweep_line(rec) -> str:
    """One EM sweep (a :class:`mmgp.labelling.convergence.SweepRecord`) on one line."""
    return (f"  sweep {rec.sweep:3d}  log p(Y,s) {rec.log_joint:12.2f}  changed {rec.changed:6.1%}  "
            f"disturbed {rec.n_disturbed:5d}  modes {rec.mode_sizes}  ({rec.seconds:.2f} s)")


class SweepProgress:
    """The EM's per-sweep callback (``MultimodalGP(progress=...)``) on a :class:`ProgressDisplay`:
    one line per sweep and a bar per number of modes tried, against ``limit`` sweeps (the
    sweep limit plus the averaged sweeps: the ETA is an upper bound, the EM may converge sooner)."""

    def __init__(self, display: ProgressDisplay, limit: int):
        self.display = display
        self.limit = limit
        self._modes = None

    def __call__(self, rec) -> None:
        k = len(rec.mode_sizes)
        if k != self._modes:
            if self._modes is not None:  # --modes auto: the sweep count restarts for each candidate
                self.display.step(f"  --modes auto: {self._modes} mode(s) done; now trying {k}")
            self._modes = k
            self.display.stage(f"EM, {k} mode(s)", self.limit)
        self.display.step(sweep_line(rec), completed=rec.sweep + 1)


def sweep_limit(settings: dict) -> int:
    """The most sweeps the EM of ``MultimodalGP(**settings)`` runs: ``max_sweeps`` + ``average_last``."""
    from ..estimator import MultimodalGP

    defaults = MultimodalGP().get_params()
    return int(settings.get("max_sweeps", defaults["max_sweeps"])) + int(settings.get("average_last",
                                                                                      defaults["average_last"]))
