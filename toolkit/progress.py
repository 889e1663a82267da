"""Progress bars of the long steps: stage 0, the physics stages and evaluation.

Every bar shows what runs (``stage 0``, ``physics 2/3 XAS@3``, ``evaluation: rendering``), the
iteration out of the total, the elapsed time and the estimated time remaining, and is drawn with
rich on stderr. Bars are off when stdout or stderr is not a terminal (logs, pipes, tests), when
the caller passes ``progress=False``, or when ``PROJO4D_PROGRESS=0``.

* :class:`IterationBar` is a Lightning progress-bar callback driven by the module's own iteration
  counter (not Lightning's batch count, which counted one ahead and had no total in stage 0);
* :func:`stage0_progress_bar` is that bar for :func:`toolkit.scene.stage0_fit.fit_stage0`
  (:func:`toolkit.physics.callbacks.curriculum_progress_bar` is the physics one);
* :func:`step_progress` is a plain bar over a known number of steps (evaluation).
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Callable, Iterator, Optional, Sequence

from pytorch_lightning.callbacks.progress.progress_bar import ProgressBar

__all__ = ["bars_enabled", "IterationBar", "StepProgress", "stage0_progress_bar", "step_progress", "format_metrics"]

#: ``(label, completed iterations, total iterations)`` of a running fit
Position = Callable[[Any, Any], "tuple[str, int, int]"]


def bars_enabled(progress: bool = True) -> bool:
    """Whether to draw bars: asked for, both stdout and stderr are terminals, and ``PROJO4D_PROGRESS`` is not ``0``."""
    if not progress or os.environ.get("PROJO4D_PROGRESS", "").strip() == "0":
        return False
    return all(getattr(s, "isatty", lambda: False)() for s in (sys.stdout, sys.stderr))


def _progress(console=None, transient: bool = False):
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(bar_width=24),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[metrics]}"),
        console=console or Console(stderr=True),
        transient=transient,
        speed_estimate_period=120.0,
    )


def format_metrics(metrics: dict, keys: Optional[Sequence[str]] = None) -> str:
    """``"loss 0.0123  n_gaussians 1234"``: the numeric entries of ``metrics`` (all, or ``keys``), 4
    significant digits, names without a ``train/`` prefix (``loss/total`` reads ``loss``)."""
    out = []
    for k, v in metrics.items():
        if keys is not None and k not in keys:
            continue
        try:
            value = float(v)
        except (TypeError, ValueError):
            continue
        name = k.removeprefix("train/")
        name = name[: -len("/total")] if name.endswith("/total") else name
        out.append(f"{name} {value:.4g}")
    return "  ".join(out)


class IterationBar(ProgressBar):
    """A Lightning progress bar over a module's own iterations.

    Args:
        position: ``position(trainer, module) -> (label, completed, total)``, called after every
            training batch (and at the start, so a resumed fit starts at its restored iteration).
        metric_keys: logged metrics shown after the bar (None: all numeric ones but ``v_num``).
        enabled: draw the bar (default :func:`bars_enabled`).
        console: a ``rich.console.Console`` to draw on (default: stderr).
    """

    def __init__(self, position: Position, metric_keys: Optional[Sequence[str]] = None, enabled: Optional[bool] = None,
                 console=None):
        super().__init__()
        self.position = position
        self.metric_keys = metric_keys
        self._enabled = bars_enabled() if enabled is None else bool(enabled)
        self._console = console
        self._bar = None
        self._task = None

    # ProgressBar interface
    def disable(self) -> None:  # noqa: D102
        self._enabled = False

    def enable(self) -> None:  # noqa: D102
        self._enabled = True

    @property
    def is_enabled(self) -> bool:  # noqa: D102
        return self._enabled

    def print(self, *args: Any, **kwargs: Any) -> None:  # noqa: D102
        if self._bar is not None:
            self._bar.console.print(*args, **kwargs)
        else:
            print(*args, **kwargs)

    # callback hooks
    def on_train_start(self, trainer, pl_module) -> None:  # noqa: D102
        if not self._enabled:
            return
        label, done, total = self.position(trainer, pl_module)
        self._bar = _progress(self._console)
        self._bar.start()
        self._task = self._bar.add_task(label, total=max(total, 1), completed=done, metrics="")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: D102
        if self._bar is None:
            return
        label, done, total = self.position(trainer, pl_module)
        metrics = format_metrics({k: v for k, v in self.get_metrics(trainer, pl_module).items() if k != "v_num"},
                                 self.metric_keys)
        self._bar.update(self._task, description=label, completed=done, total=max(total, 1), metrics=metrics)

    def on_train_end(self, trainer, pl_module) -> None:  # noqa: D102
        self._stop()

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:  # noqa: D102
        self._stop()

    def teardown(self, trainer, pl_module, stage: str) -> None:  # noqa: D102
        self._stop()

    def _stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def _stage0_position(trainer, module) -> tuple[str, int, int]:
    total = int(module.schedule.iterations)
    if module.stop_at is not None:
        total = min(total, int(module.stop_at))
    done = int(module.step)
    phase = "static warm-up" if done < int(module.schedule.warmup) else "dynamic"
    return f"stage 0 ({phase})", min(done, total), total


def stage0_progress_bar(enabled: Optional[bool] = None, console=None) -> IterationBar:
    """The bar of stage 0: ``stage 0 (static warm-up|dynamic)``, iteration/total of its schedule, ETA, loss."""
    return IterationBar(_stage0_position, metric_keys=("train/loss", "train/n_gaussians"), enabled=enabled, console=console)


class StepProgress:
    """Handle of :func:`step_progress`: ``advance(what)`` after each step (``what`` names the next)."""

    def __init__(self, bar, task, label: str):
        self._bar, self._task, self.label = bar, task, label
        self.completed = 0

    def advance(self, what: Optional[str] = None, steps: int = 1) -> None:
        """One step (or ``steps``) done; ``what`` describes the work that follows."""
        self.completed += steps
        if self._bar is not None:
            kw = {"description": f"{self.label}: {what}"} if what else {}
            self._bar.update(self._task, advance=steps, **kw)

    def describe(self, what: str) -> None:
        """Say what runs now without advancing."""
        if self._bar is not None:
            self._bar.update(self._task, description=f"{self.label}: {what}")


@contextlib.contextmanager
def step_progress(label: str, total: int, progress: bool = True, console=None) -> Iterator[StepProgress]:
    """A bar over ``total`` steps labelled ``label`` (off as :func:`bars_enabled` says).

    Example::

        with step_progress("evaluation", 3) as bar:
            bar.describe("predicting")
            ...
            bar.advance("metrics")
    """
    if not (bars_enabled(progress) or (progress and console is not None)):
        yield StepProgress(None, None, label)
        return
    bar = _progress(console)
    task = bar.add_task(label, total=max(total, 1), metrics="")
    bar.start()
    try:
        yield StepProgress(bar, task, label)
    finally:
        bar.stop()
