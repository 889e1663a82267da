"""Run a documentation page's Python blocks in a fresh process that starts with the heavy imports done.

A new interpreter per page spent 8-9 s of CI's CPU importing torch, Lightning and Warp before the
page's first line ran (12 pages). :class:`PageRunner` starts one *zygote* interpreter that imports
:data:`PRELOAD` and runs nothing else; each page then runs in a child forked from it. The child is
as fresh as a new interpreter after those imports: a new ``__main__`` module named after the page
(Warp and ``inspect`` find a page's functions at the page's line numbers), its own working
directory and output files, and whatever a page registers, sets or leaks dies with its child, as
the zygote never runs a page. Needs ``os.fork`` (Linux, macOS); :func:`run_page_fresh` is the plain
new-interpreter run, used where fork is missing.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

__all__ = ["PRELOAD", "PageRunner", "run_page_fresh"]

#: modules the zygote imports (importing them registers nothing a page could not register itself)
PRELOAD = ("numpy", "torch", "pytorch_lightning", "warp", "matplotlib.pyplot", "toolkit.pipeline", "toolkit.physics",
           "toolkit.synthetic")

# the page's blocks in a new __main__; the child exits as an interpreter would (exit handlers run)
_RUN_BLOCKS = r"""
def run_blocks(page, blocks):
    import sys, types
    main = types.ModuleType("__main__")
    main.__file__ = page
    sys.modules["__main__"] = main
    sys.argv = [page]
    for line, code in blocks:
        print(f"--- {page}:{line}", flush=True)
        exec(compile("\n" * (line - 1) + code, page, "exec"), main.__dict__)
"""

_FRESH = _RUN_BLOCKS + r"""
import json, sys
run_blocks(sys.argv[1], json.load(open(sys.argv[2])))
"""

_ZYGOTE = _RUN_BLOCKS + r"""
import atexit, importlib, json, os, sys, traceback
for name in sys.argv[1:]:
    importlib.import_module(name)
print("ready", flush=True)
for request in sys.stdin:
    req = json.loads(request)
    pid = os.fork()
    if pid == 0:
        status = 1
        try:
            os.chdir(req["cwd"])
            for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                os.dup2(f, fd)
                os.close(f)
            null = os.open(os.devnull, os.O_RDONLY)
            os.dup2(null, 0)
            sys.stdin = open(os.devnull)  # not the zygote's buffered request pipe
            run_blocks(req["page"], req["blocks"])
            status = 0
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:
            traceback.print_exc()
        try:
            atexit._run_exitfuncs()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
    print(json.dumps({"pid": pid}), flush=True)
    _, wait_status = os.waitpid(pid, 0)
    print(json.dumps({"exit": os.waitstatus_to_exitcode(wait_status)}), flush=True)
"""


def run_page_fresh(page: Path, blocks: list, cwd: Path, env: dict, timeout: float) -> tuple[int, str, str]:
    """The page's ``blocks`` (``[(line, code), ...]``) in a new interpreter: ``(exit code, stdout, stderr)``."""
    blocks_file = Path(cwd).parent / "blocks.json"
    blocks_file.write_text(json.dumps(blocks))
    proc = subprocess.run([sys.executable, "-c", _FRESH, str(page), str(blocks_file)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stdout, proc.stderr


class PageRunner:
    """A zygote interpreter with :data:`PRELOAD` imported; :meth:`run` forks a child per page.

    Args:
        env: the zygote's environment (the children inherit it).
        cwd: the zygote's working directory.
    """

    def __init__(self, env: dict, cwd: Path):
        self._log = tempfile.NamedTemporaryFile(prefix="page_zygote_", suffix=".log", delete=False)
        self._proc = subprocess.Popen([sys.executable, "-c", _ZYGOTE, *PRELOAD], cwd=cwd, env=env, text=True,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log)
        self._lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        line = ""
        while line != "ready":  # a preloaded module may print on import
            line = self._lines.get(timeout=300)
            if line is None:
                raise RuntimeError(f"the page zygote did not start: {Path(self._log.name).read_text()[-4000:]}")

    def _read(self) -> None:
        for line in self._proc.stdout:
            self._lines.put(line.strip())
        self._lines.put(None)

    def _next(self, timeout: float | None) -> dict:
        line = self._lines.get(timeout=timeout)
        if line is None:
            raise RuntimeError(f"the page zygote died: {Path(self._log.name).read_text()[-4000:]}")
        return json.loads(line)

    def run(self, page: Path, blocks: list, cwd: Path, timeout: float) -> tuple[int, str, str]:
        """The page's ``blocks`` (``[(line, code), ...]``) in a child run in ``cwd``: ``(exit code,
        stdout, stderr)``; a child still running after ``timeout`` seconds is killed (exit -9)."""
        out, err = Path(cwd).parent / "stdout.txt", Path(cwd).parent / "stderr.txt"
        request = {"page": str(page), "blocks": blocks, "cwd": str(cwd), "stdout": str(out), "stderr": str(err)}
        self._proc.stdin.write(json.dumps(request) + "\n")
        self._proc.stdin.flush()
        pid = self._next(60)["pid"]
        try:
            code = self._next(timeout)["exit"]
        except queue.Empty:
            os.kill(pid, signal.SIGKILL)
            code = self._next(60)["exit"]
        return code, out.read_text(errors="replace"), err.read_text(errors="replace")

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._proc.kill()
        self._log.close()
        os.unlink(self._log.name)
