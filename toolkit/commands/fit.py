"""``projo4d fit``: the physics stages under LightningCLI (YAML configs, every argument overridable).

Examples::

    projo4d fit --config configs/synthetic_elastic.yaml
    projo4d fit --config configs/synthetic_elastic.yaml --model.curriculum sequential --trainer.default_root_dir runs/seq
    projo4d fit --model.input_path RUN/physics_input.pt --model.material plasticine --model.curriculum "XAS:100@3,XASM:300"
    projo4d fit --config RUN/logs/version_0/config.yaml --ckpt_path RUN/checkpoints/last.ckpt   # resume

The model is :class:`toolkit.physics.InversePhysicsModule`; its ``curriculum`` takes a strategy
name, a schedule string or ``class_path``/``init_args`` of any :class:`strategies.Strategy`
subclass (yours included). The resolved config is saved next to the logs.

Loggers: CSV (and TensorBoard when installed) under ``<default_root_dir>/logs`` unless
``--trainer.logger`` names others (or ``false``). Callbacks the user adds
(``--trainer.callbacks+=ModelCheckpoint``) run beside ours (curriculum checkpoints, estimate
writer); a ``ModelCheckpoint`` turns Lightning's checkpointing on for it.
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
            parser.add_argument("--run", type=Optional[dict], default=None,
                                help="pipeline settings (used by `projo4d run` and `projo4d stage0`; keys are RunSettings "
                                     "fields, unknown keys are errors)")

        def before_instantiate_classes(self) -> None:
            from toolkit.run_config import check_run_section

            check_run_section(self._get(self.config, "run"), "projo4d fit")

        def instantiate_trainer(self, **kwargs):
            from pytorch_lightning.callbacks import ModelCheckpoint

            # our checkpoints are CurriculumCheckpoint's (enable_checkpointing=False keeps Lightning's
            # default one away); a ModelCheckpoint the user adds turns Lightning's checkpointing on
            trainer_cfg = self._get(self.config_init, "trainer", default={})
            user = trainer_cfg.get("callbacks") or []
            user = list(user) if isinstance(user, (list, tuple)) else [user]
            user += [self._get(self.config_init, c) for c in self._parser(self.subcommand).callback_keys]
            if any(isinstance(cb, ModelCheckpoint) for cb in user) and trainer_cfg.get("enable_checkpointing") is False:
                kwargs.setdefault("enable_checkpointing", True)
            return super().instantiate_trainer(**kwargs)

        def before_fit(self) -> None:
            from pytorch_lightning.callbacks import ProgressBar

            from toolkit.physics.callbacks import curriculum_progress_bar
            from toolkit.physics.fit import default_loggers

            # unless the user chose loggers (--trainer.logger), they live under the run folder of
            # --trainer.default_root_dir: CSV, and TensorBoard when installed
            if self._get(self.config, "trainer", default={}).get("logger") in (None, True):
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
