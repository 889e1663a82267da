"""The generated command-line reference (docs/_ext/cli_reference.py) matches the parsers."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

DOCS_EXT = Path(__file__).resolve().parents[1] / "docs" / "_ext"


@pytest.fixture(scope="module")
def cli_reference():
    sys.path.insert(0, str(DOCS_EXT))
    try:
        import cli_reference

        yield cli_reference
    finally:
        sys.path.remove(str(DOCS_EXT))


def test_fit_model_section_cuts_one_group(cli_reference):
    help_text = "\n".join([
        "usage: projo4d fit ...",
        "Trainer options:",
        "  --trainer.max_steps MAX_STEPS",
        "",
        "Fit the physics:",
        "  --model CONFIG        Path to a configuration file.",
        "  --model.material MATERIAL",
        "                        material name",
        "",
        "  --model.seed SEED     seed",
        "A DataModule ...",
        "  --data CONFIG",
    ])
    section = cli_reference.fit_model_section(help_text)
    assert section.splitlines()[0] == "Fit the physics:"
    assert section.splitlines()[-1] == "  --model.seed SEED     seed"
    assert "--trainer" not in section and "--data" not in section
    with pytest.raises(RuntimeError, match="no `--model CONFIG` option"):
        cli_reference.fit_model_section("usage: nothing\n")


def test_every_command_has_a_section_with_its_own_help(cli_reference):
    from toolkit import cli

    page = cli_reference.generate()
    headings = [ln for ln in page.splitlines() if ln.startswith("## ")]
    assert headings == ["## `projo4d`"] + [f"## `projo4d {name}`" for name in cli.COMMANDS]
    # each section holds what that parser prints (argparse usage line), fit its --model.* options
    for name in cli.COMMANDS:
        section = page.split(f"## `projo4d {name}`", 1)[1].split("\n## ", 1)[0]
        if name == "fit":
            assert "--model.input_path" in section and "--model.curriculum" in section
            assert "--trainer.max_steps" not in section  # Lightning's own arguments are summarized, not listed
        else:
            assert f"usage: projo4d {name}" in section, name
    run_section = page.split("## `projo4d run`", 1)[1].split("\n## ", 1)[0]
    parser = cli._build_parser_for(["run"])
    run_options = {s for a in parser._subparsers._group_actions[0].choices["run"]._actions for s in a.option_strings}
    assert run_options and all(opt in run_section for opt in run_options)
