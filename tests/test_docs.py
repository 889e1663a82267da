"""The documentation site: every page's Python code runs, and Sphinx builds it without a warning.

Convention (docs/README.md): on every Markdown page under ``docs/``, each fenced code block whose
language is exactly ``python`` is executed, in page order, in one fresh namespace per page, in a
fresh process (forked from one that has imported the heavy libraries and run nothing else:
`tests/page_runner.py`), in a temporary working directory, on the CPU. Python that must not run (GPU
only, needs a download, illustrates a file) goes in a ``{code-block} python`` directive instead;
those blocks are only compiled, so they at least stay valid syntax.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGE_TIMEOUT_S = 600

_FENCE = re.compile(r"^(?P<fence>`{3,}|~{3,})(?P<info>.*)$")
# directives whose body is Markdown again (admonitions, figures, ...) are searched for code
# blocks; these hold code
_CODE_DIRECTIVES = {"code-block", "code", "sourcecode", "code-cell"}


@dataclass
class Block:
    line: int  # 1-based line of the first code line in the page
    code: str
    runs: bool  # executed (```python) or only compiled ({code-block} python)


def pages() -> list[Path]:
    """Every authored Markdown page (not the contributor notes, not generated or built files)."""
    out = []
    for path in sorted(DOCS.rglob("*.md")):
        rel = path.relative_to(DOCS)
        if rel.parts[0] in ("_build", "_ext") or rel.parts[:2] == ("reference", "api") or rel == Path("README.md"):
            continue
        out.append(path)
    return out


def extract_blocks(text: str, first_line: int = 1) -> list[Block]:
    """The Python code blocks of a MyST page, in order (see the module docstring)."""
    lines = text.splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, info = m.group("fence"), m.group("info").strip()
        end = i + 1
        while end < len(lines) and not (
            lines[end].startswith(fence[0] * len(fence)) and lines[end].strip() == fence[0] * len(lines[end].strip())
        ):
            end += 1
        body = lines[i + 1 : end]
        body_line = first_line + i + 1
        words = info.split()
        if info == "python":
            blocks.append(Block(body_line, "\n".join(body) + "\n", True))
        elif words and words[0].startswith("{") and words[0].endswith("}"):
            name = words[0][1:-1]
            # skip the directive's options: ``:key: value`` lines, or a ``---`` YAML block
            k = 0
            if body and body[0].strip() == "---":
                k = 1
                while k < len(body) and body[k].strip() != "---":
                    k += 1
                k += 1
            else:
                while k < len(body) and body[k].startswith(":"):
                    k += 1
            if name in _CODE_DIRECTIVES:
                if len(words) > 1 and words[1] in ("python", "python3", "py"):
                    blocks.append(Block(body_line + k, "\n".join(body[k:]) + "\n", False))
            else:
                blocks.extend(extract_blocks("\n".join(body[k:]), body_line + k))
        i = end + 1
    return blocks


def test_extract_blocks_convention():
    page = "\n".join([
        "# Title",  # 1
        "```python",  # 2
        "a = 1",  # 3
        "```",  # 4
        "```bash",  # 5
        "echo not python",  # 6
        "```",  # 7
        "````{note}",  # 8
        "```python",  # 9
        "b = a + 1",  # 10
        "```",  # 11
        "````",  # 12
        "```{code-block} python",  # 13
        ":caption: not run",  # 14
        "import cuda_only_thing",  # 15
        "```",  # 16
    ])
    blocks = extract_blocks(page)
    assert [(b.line, b.code.strip(), b.runs) for b in blocks] == [
        (3, "a = 1", True),
        (10, "b = a + 1", True),
        (15, "import cuda_only_thing", False),
    ]


PAGES = pages()


def test_every_tutorial_runs_code():
    tutorials = [p for p in PAGES if p.parent.name == "tutorials"]
    assert tutorials, "no tutorial pages found"
    for page in tutorials:
        assert any(b.runs for b in extract_blocks(page.read_text())), f"{page} has no executed ```python block"


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(DOCS)) for p in PAGES])
def test_non_executed_python_compiles(page: Path):
    for block in extract_blocks(page.read_text()):
        if not block.runs:
            compile("\n" * (block.line - 1) + block.code, str(page), "exec")


# Runs in a fresh process (tests/page_runner.py: forked from one that has imported torch,
# Lightning and Warp and run nothing else, or a new interpreter where fork is missing): a page's
# code gets a clean module namespace (its functions can be Warp functions: they are compiled with
# the page as their source file, at the page's line numbers, so Warp and inspect find their
# source) and cannot leak registrations, Warp settings or the working directory into the test
# process or into other pages.


def _cpu_env() -> dict[str, str]:
    env = dict(os.environ)
    env["CUDA_VISIBLE_DEVICES"] = ""  # tutorials run on the CPU, also on a GPU machine
    env["MPLBACKEND"] = "Agg"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


RUNNABLE = [p for p in PAGES if any(b.runs for b in extract_blocks(p.read_text()))]


@pytest.fixture(scope="session")
def page_runner():
    """One zygote per test worker, started at the first page it runs (None without ``os.fork``)."""
    if not hasattr(os, "fork"):
        yield None
        return
    from tests.page_runner import PageRunner

    runner = PageRunner(_cpu_env(), ROOT)
    yield runner
    runner.close()


@pytest.mark.parametrize("page", RUNNABLE, ids=[str(p.relative_to(DOCS)) for p in RUNNABLE])
def test_page_code_runs(page: Path, tmp_path: Path, page_runner):
    from tests.page_runner import run_page_fresh

    blocks = [(b.line, b.code) for b in extract_blocks(page.read_text()) if b.runs]
    work = tmp_path / "work"
    work.mkdir()
    if page_runner is not None:
        code, out, err = page_runner.run(page, blocks, work, PAGE_TIMEOUT_S)
    else:
        code, out, err = run_page_fresh(page, blocks, work, _cpu_env(), PAGE_TIMEOUT_S)
    if code != 0:
        text = (out[-4000:] + "\n" + err[-8000:]).strip()
        pytest.fail(f"the code of {page.relative_to(ROOT)} failed (exit {code}):\n{text}")


@pytest.mark.slow
def test_sphinx_build_has_no_warnings(tmp_path: Path):
    """``make docs`` in a temporary output folder: warnings are errors, and none may appear.

    Built with Sphinx's ``basic`` theme instead of the site's furo: furo lays out the whole
    navigation tree (every API page) on each of the ~200 pages, which is half of the build's time
    on CI's 2 cores, and the pages, the API reference, the math and the warnings are the theme's
    inputs, not its output. ``make docs`` keeps furo."""
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-E", "-q", "-b", "html", "-D", "html_theme=basic",
         "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )
    output = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 0, f"sphinx failed:\n{output[-8000:]}"
    assert "WARNING" not in output and "ERROR" not in output, output[-8000:]
    assert (tmp_path / "html" / "index.html").is_file()
    assert (tmp_path / "html" / "reference" / "api" / "toolkit" / "toolkit.mpm.simulator.html").is_file()
    # math offline: MathJax is served from the site itself, not from a CDN
    concepts = (tmp_path / "html" / "concepts.html").read_text()
    assert 'src="_static/mathjax/tex-chtml.js"' in concepts and "cdn.jsdelivr" not in concepts
    assert (tmp_path / "html" / "_static" / "mathjax" / "output" / "chtml" / "fonts" / "woff-v2").is_dir()
    # the command-line reference has a section per command, generated from the parsers
    from toolkit.cli import COMMANDS

    cli_page = (tmp_path / "html" / "reference" / "cli.html").read_text()
    for name in COMMANDS:
        assert f'id="projo4d-{name}"' in cli_page, name
    assert "--model.curriculum" in cli_page and "usage: projo4d run" in cli_page


def test_page_runner_isolates_pages_and_reports_failures(page_runner, tmp_path: Path):
    """What one page sets or registers does not reach the next; a failure names the page's line;
    an exit status and a timeout come back as the exit code."""
    if page_runner is None:
        pytest.skip("no os.fork here: pages run in new interpreters")

    def run(name: str, blocks: list, timeout: float = 120):
        work = tmp_path / name / "work"
        work.mkdir(parents=True)
        return page_runner.run(tmp_path / f"{name}.md", blocks, work, timeout)

    leak = "import os, toolkit\ntoolkit._leaked = 1\nos.environ['PAGE_LEAK'] = '1'\nprint(os.getcwd())\n"
    code, out, _ = run("a", [(3, leak)])
    assert code == 0 and out.splitlines()[-1] == str(tmp_path / "a" / "work")
    check = ("import os, sys, toolkit\nassert not hasattr(toolkit, '_leaked') and 'PAGE_LEAK' not in os.environ\n"
             "assert __name__ == '__main__' and __file__.endswith('b.md') and sys.modules['__main__'].__file__ == __file__\n")
    assert run("b", [(1, check)])[0] == 0
    code, _, err = run("c", [(1, "x = 1\n"), (7, "\nraise ValueError('boom')\n")])
    assert code == 1 and "ValueError: boom" in err and 'c.md", line 8' in err
    assert run("d", [(1, "import sys\nsys.exit(3)\n")])[0] == 3
    assert run("e", [(1, "import time\ntime.sleep(60)\n")], timeout=1)[0] == -9
    assert run("f", [(1, "print('after a kill')\n")])[1].splitlines()[-1] == "after a kill"
