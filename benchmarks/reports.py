"""The benchmarks' result files: a markdown report and its numbers as JSON beside it."""

from __future__ import annotations

import json
import pathlib
import subprocess


def write_results(out, lines: list[str], numbers: dict) -> str:
    """Print the report `lines` and write them to `out` (markdown) and `numbers` to `out` with a .json suffix;
    returns the report's text."""
    text = "\n".join(lines)
    print(text)
    out = pathlib.Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(numbers, indent=1))
    return text


def run_workers(commands: list, jobs: int, tag: str) -> list[dict]:
    """Run worker processes, `jobs` at a time, in order: each command (argv, env, cwd) prints its result as one line,
    `tag` followed by JSON. Returns the results in the commands' order."""
    results, running, queue = [None] * len(commands), {}, list(enumerate(commands))
    while queue or running:
        while queue and len(running) < max(1, jobs):
            k, (argv, env, cwd) = queue.pop(0)
            running[k] = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=cwd)
        k = next(iter(running))
        proc = running.pop(k)
        out, _ = proc.communicate()
        found = [line[len(tag):] for line in out.splitlines() if line.startswith(tag)]
        if not found:  # (named by its own command, not the last one started)
            raise RuntimeError(f"a worker ({' '.join(map(str, proc.args[2:]))}) exited without a result (code {proc.returncode})")
        results[k] = json.loads(found[-1])
    return results
