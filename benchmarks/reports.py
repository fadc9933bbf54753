"""The benchmarks' result files: a markdown report and its numbers as JSON beside it."""

from __future__ import annotations

import json
import pathlib


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
