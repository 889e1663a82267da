"""``projo4d fit``: the physics stages under LightningCLI (YAML configs, every argument overridable).

Examples::

    projo4d fit --config configs/synthetic_elastic.yaml
    projo4d fit --config configs/synthetic_elastic.yaml --model.curriculum sequential --trainer.default_root_dir runs/seq
    projo4d fit --model.input_path RUN/physics_input.pt --model.material plasticine --model.curriculum "XAS:100@3,XASM:300"
    projo4d fit --config RUN/logs/version_0/config.yaml --ckpt_path RUN/checkpoints/last.ckpt   # resume

The model is :class:`toolkit.physics.InversePhysicsModule`; its ``curriculum`` takes a strategy
name, a schedule string or ``class_path``/``init_args`` of any :class:`strategies.Strategy`
subclass (yours included). The resolved config is saved next to the logs.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

__all__ = ["configure", "run", "main"]


def configure(parser: argparse.ArgumentParser) -> None:  # arguments are LightningCLI's own
    parser.add_argument("args", nargs=argparse.REMAINDER, help="LightningCLI arguments (see `projo4d fit --help`)")


def run(args: argparse.Namespace) -> int:
    return main(args.args)


def main(argv: Sequence[str] | None = None) -> int:
    from pytorch_lightning.cli import LightningCLI

    from toolkit.physics.fit import TRAINER_DEFAULTS, default_callbacks
    from toolkit.physics.module import InversePhysicsModule

    argv = list(sys.argv[2:] if argv is None else argv)
    if not argv or argv[0] != "fit":
        argv = ["fit", *argv]

    class PhysicsCLI(LightningCLI):
        def add_arguments_to_parser(self, parser) -> None:
            # configs/ files carry a `run:` section for `projo4d run` (stage 0, cameras, split)
            parser.add_argument("--run", type=Optional[dict], default=None, help="pipeline settings (used by `projo4d run`)")

        def before_fit(self) -> None:
            from pytorch_lightning.callbacks import ProgressBar

            from toolkit.physics.callbacks import curriculum_progress_bar
            from toolkit.physics.fit import default_loggers

            # loggers live under the run folder chosen by --trainer.default_root_dir
            self.trainer.loggers = default_loggers(self.trainer.default_root_dir)
            # Lightning's default bar (when enabled) becomes the stage-aware one
            cbs = self.trainer.callbacks
            for i, cb in enumerate(cbs):
                if isinstance(cb, ProgressBar):
                    cbs[i] = curriculum_progress_bar()

    from toolkit.checkpointing import graceful_interrupts

    with graceful_interrupts():  # Ctrl-C / SIGTERM: save last.ckpt at the end of the iteration, then stop
        PhysicsCLI(
            InversePhysicsModule,
            trainer_defaults={**TRAINER_DEFAULTS, "callbacks": default_callbacks(progress=False), "default_root_dir": "runs/fit"},
            save_config_kwargs={"overwrite": True},
            parser_kwargs={"exit_on_error": False},  # a mistake is one line from toolkit.cli's error boundary
            args=argv,
            auto_configure_optimizers=False,
        )
    return 0
