"""Kernel hygiene: a kernel writes only parameters named *_out (the tape rule as a test), all kernels live in kernels/."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
KERNEL_FILES = sorted((ROOT / "kernels").glob("*.py"))
ATOMICS = {"atomic_add", "atomic_sub", "atomic_max", "atomic_min"}


def is_warp_decorator(dec, name):
    target = dec.func if isinstance(dec, ast.Call) else dec
    return isinstance(target, ast.Attribute) and target.attr == name


def written_names(fn):
    """Names of arrays the function stores into (subscript assignment, augmented assignment, atomics)."""
    out = []
    for node in ast.walk(fn):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, ast.AugAssign):
            targets = [node.target]
        for t in targets:
            if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name):
                out.append((t.value.id, node.lineno))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ATOMICS:
            if node.args and isinstance(node.args[0], ast.Name):
                out.append((node.args[0].id, node.lineno))
    return out


@pytest.mark.parametrize("path", KERNEL_FILES, ids=lambda p: p.name)
def test_kernels_write_only_out_parameters(path):
    """Check every Warp kernel and function stores only into parameters whose name ends in _out."""
    tree = ast.parse(path.read_text())
    bad = []
    for fn in tree.body:
        if not isinstance(fn, ast.FunctionDef):
            continue
        if not any(is_warp_decorator(d, "kernel") or is_warp_decorator(d, "func") for d in fn.decorator_list):
            continue
        params = {a.arg for a in fn.args.args}
        for name, line in written_names(fn):
            if name in params and not name.endswith("_out"):
                bad.append(f"{path.name}:{line} {fn.name} writes input {name!r}")
    assert not bad, "\n".join(bad)


# Spelled in two parts so that this file does not match its own search.
DECORATORS = ("@wp." + "kernel", "@wp." + "func")


def test_no_kernels_outside_kernels_package():
    """Check no Warp kernel or function is defined outside kernels/ (each module is one more cold compile)."""
    offenders = []
    for path in list((ROOT / "cloth_warp").rglob("*.py")) + list((ROOT / "tests").glob("*.py")) + list((ROOT / "benchmarks").glob("*.py")):
        text = path.read_text()
        if any(d in text for d in DECORATORS):
            offenders.append(str(path.relative_to(ROOT)))
    assert offenders == [], offenders
