"""Shared fixtures: the device list (cpu always, cuda:0 when present) and model helpers."""

import contextlib
import os

import numpy as np
import pytest
import warp as wp

wp.config.log_level = wp.LOG_WARNING
# CLOTH_WARP_VERIFY_CUDA=1: a CUDA kernel that faults raises at its own launch, in its own test (a synchronisation
# per launch), instead of poisoning the process's context for every later test of that worker
wp.config.verify_cuda = bool(os.environ.get("CLOTH_WARP_VERIFY_CUDA"))
wp.init()
# Tests without a `device` parameter run on the CPU on every machine, as in CI: on a GPU machine Warp's default
# device is cuda:0, and a helper array made without a device beside a CPU model was read by a kernel on the
# wrong device (illegal memory accesses that poisoned the worker's CUDA context for every later test). The tests
# that take `device` run on each device in DEVICES explicitly.
wp.set_device("cpu")

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


def _refused_in_device_bodies(name, allocate):
    """`allocate` that fails inside a device loop or branch body: CUDA refuses to record an allocation there, so the
    CPU suite must not let one pass (cloth_warp.graphs.in_device_body)."""
    from cloth_warp.graphs import in_device_body

    def guarded(*args, **kwargs):
        if in_device_body():
            raise AssertionError(f"wp.{name} inside a device loop or branch body (CUDA cannot record it): allocate before the loop")
        return allocate(*args, **kwargs)

    return guarded


@contextlib.contextmanager
def host_probe():
    """A test's own host-side checks inside an eagerly run device body (never recorded): allocations allowed there."""
    from cloth_warp import graphs

    depth, graphs._Bodies.depth = graphs._Bodies.depth, 0
    try:
        yield
    finally:
        graphs._Bodies.depth = depth


for _name in ("zeros", "zeros_like", "empty", "empty_like", "full", "full_like", "ones", "ones_like", "clone"):
    setattr(wp, _name, _refused_in_device_bodies(_name, getattr(wp, _name)))


def pytest_addoption(parser):
    parser.addoption("--device", action="store", default=None, help="run only on this Warp device (cpu, cuda:0)")


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        chosen = metafunc.config.getoption("--device")
        devices = [chosen] if chosen else DEVICES
        metafunc.parametrize("device", devices, ids=[d.replace(":", "_") for d in devices])


def recordable(solver, model) -> bool:
    """Whether two forward steps of `solver` can be recorded as a graph and replayed (bit for bit the eager steps:
    tests/test_capture.py): passes on paths that can be recorded (self-collision's host path cannot), no animated
    control, loops on a device that can capture them."""
    return solver.capturable and not model.animated and (model.device.is_cpu or wp.is_conditional_graph_supported())


def run_steps(solver, model, steps, dt, state=None, control=None, record=None):
    """Advance `steps` steps with two swapped states; `record(k, state)` after each step. Without `record`, pairs of
    untaped steps are recorded once as a graph and replayed (the same kernels, the same results, far fewer launches)."""
    s0 = state or model.state()
    s1 = model.state()
    control = control or model.control()
    if record is None and steps >= 4 and not s0.requires_grad and recordable(solver, model):
        s0, s1 = wp.clone(s0.particle_q), wp.clone(s0.particle_qd)  # the caller's state is not overwritten
        from cloth_warp.model import State

        a, b = State(s0, s1), model.state()
        with wp.ScopedCapture(device=model.device) as cap:
            solver.step(a, b, control, dt)
            solver.step(b, a, control, dt)
        for _ in range(steps // 2):
            wp.capture_launch(cap.graph)
        if steps % 2:
            solver.step(a, b, control, dt)
            return b
        return a
    for k in range(steps):
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
        if record is not None:
            record(k, s0)
    return s0


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
