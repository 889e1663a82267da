"""``projo4d stage0``: only stage 0 (the 4D Gaussians) of a scene, in a run folder.

It takes the same arguments and config file as ``projo4d run`` and checks them the same way before
any work; a later ``projo4d run`` with the same folder and stage-0 settings reuses this stage 0
(see :mod:`toolkit.stage0_only`). Rerunning the same command resumes where it stopped.

Examples::

    projo4d stage0 scenes/torus --out runs/torus --stage0 tiny --device cpu
    projo4d run scenes/torus --out runs/torus --stage0 tiny --device cpu   # reuses that stage 0
    projo4d stage0 --config configs/pacnerf_sand.yaml --scene data/pacnerf/sand/0 --out runs/sand0
"""

from __future__ import annotations

import argparse

from toolkit.commands import run as run_command
from toolkit.run_validation import SettingsError

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    """The arguments of ``projo4d run`` (the settings stage 0 ignores are checked and recorded for the run)."""
    run_command.configure(parser)


def run(args: argparse.Namespace) -> int:
    if args.resume and args.overwrite:
        raise SettingsError("--resume/--overwrite", True, "give one of them, not both")
    mode = "resume" if args.resume else "overwrite" if args.overwrite else "auto"
    settings = run_command.settings_from_args(args, "stage0")
    settings.check_fields()  # a typo is reported before torch and Lightning load
    from toolkit.stage0_only import format_stage0_summary, run_stage0

    summary = run_stage0(settings, mode=mode)
    print(format_stage0_summary(summary))
    return 0
