"""The commands of a tutorial page, as a reader runs them: extracted from the page and run in order.

A page marks each code block a reader runs with an HTML comment on the line before its opening fence:

- `<!-- tutorial: run -->`: run it (bash, from the repository root); it must exit 0;
- `<!-- tutorial: background NAME -->`: a long-running program started in a terminal of its own; it keeps running
  while the following blocks run;
- `<!-- tutorial: stop NAME -->` (no block): the reader presses Ctrl-C in NAME's terminal (SIGINT).

Background programs still running at the end of the page are stopped the same way. Blocks without a marker are
not run (output shown to the reader, files to write by hand, commands for another machine).

`python -m scripts.docsgen.tutorials docs/tutorials/PAGE.md` runs one page as the tests do.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from scripts.docsgen.markdown import ROOT

_MARKER = re.compile(r"^<!-- tutorial: (run|background|stop)(?: ([\w-]+))? -->$")
_FENCE = re.compile(r"^```(\w*)\s*$")


@dataclass(frozen=True)
class Step:
    """One marked step of a page: `kind` run | background | stop, the background program's `name`, the commands
    (`script`, empty for stop) and the page line of the marker (for error messages)."""

    kind: str
    name: str
    script: str
    line: int


def steps(page: Path) -> list[Step]:
    """The marked steps of `page`, in page order; raises ValueError naming the line of a malformed marker."""
    lines = page.read_text(encoding="utf-8").splitlines()
    out: list[Step] = []
    i = 0
    while i < len(lines):
        text = lines[i].strip()
        if text.startswith("<!-- tutorial:"):
            match = _MARKER.match(text)
            if match is None:
                raise ValueError(f"{page}:{i + 1}: malformed tutorial marker {text!r}; expected "
                                 "'<!-- tutorial: run -->', '<!-- tutorial: background NAME -->' or "
                                 "'<!-- tutorial: stop NAME -->'")
            kind, name = match.group(1), match.group(2) or ""
            if (kind in ("background", "stop")) != bool(name):
                raise ValueError(f"{page}:{i + 1}: '{kind}' {'needs' if kind != 'run' else 'takes no'} a name")
            if kind == "stop":
                out.append(Step(kind, name, "", i + 1))
            else:
                if i + 1 >= len(lines) or not _FENCE.match(lines[i + 1].strip()):
                    raise ValueError(f"{page}:{i + 1}: a '{kind}' marker must stand right above a fenced code block")
                end = next((j for j in range(i + 2, len(lines)) if lines[j].strip() == "```"), None)
                if end is None:
                    raise ValueError(f"{page}:{i + 2}: code block never closed")
                out.append(Step(kind, name, "\n".join(lines[i + 2:end]), i + 1))
                i = end
        i += 1
    return out


def environment() -> dict[str, str]:
    """The reader's environment: the project's `.venv/bin` (or this interpreter's) first on PATH, the checkout on
    PYTHONPATH, so `ddvs` and `python` are the project's."""
    env = dict(os.environ)
    venv_bin = ROOT / ".venv" / "bin"
    bin_dir = venv_bin if venv_bin.is_dir() else Path(sys.executable).parent
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = str(ROOT)
    return env


def _interrupt(proc: subprocess.Popen[bytes], grace_s: float = 15.0) -> int:
    """Ctrl-C in the program's terminal: SIGINT to its process group; SIGKILL if it has not exited after grace_s."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def run_page(page: Path, log_dir: Path, step_timeout_s: float = 600.0) -> None:
    """Run the steps of `page` from the repository root; raises RuntimeError naming the failing step, with the end
    of its output. Each background program's output goes to `log_dir/<name>.log`."""
    log_dir.mkdir(parents=True, exist_ok=True)
    env = environment()
    background: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for step in steps(page):
            if step.kind == "background":
                log = (log_dir / f"{step.name}.log").open("wb")
                background[step.name] = subprocess.Popen(["bash", "-c", step.script], cwd=ROOT, env=env,
                                                         stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
                time.sleep(1.0)
            elif step.kind == "stop":
                if step.name not in background:
                    raise RuntimeError(f"{page}:{step.line}: stop {step.name!r}, which was never started")
                _interrupt(background.pop(step.name))
            else:
                done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", step.script], cwd=ROOT, env=env,
                                      capture_output=True, text=True, timeout=step_timeout_s)
                if done.returncode != 0:
                    raise RuntimeError(f"{page}:{step.line}: exit status {done.returncode} of\n{step.script}\n"
                                       f"--- output (end) ---\n{(done.stdout + done.stderr)[-3000:]}")
            for name, proc in background.items():
                if proc.poll() is not None:
                    tail = (log_dir / f"{name}.log").read_text(encoding="utf-8", errors="replace")[-3000:]
                    raise RuntimeError(f"{page}: background program {name!r} exited with status {proc.returncode}"
                                       f" before it was stopped; end of its output:\n{tail}")
    finally:
        for proc in background.values():
            _interrupt(proc)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m scripts.docsgen.tutorials docs/tutorials/PAGE.md", file=sys.stderr)
        return 2
    page = Path(args[0]).resolve()
    run_page(page, ROOT / "reports" / "tutorial-logs" / page.stem)
    print(f"{page.name}: every step ran")
    return 0


if __name__ == "__main__":
    sys.exit(main())
