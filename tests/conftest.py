"""Shared fixtures: the device list (cpu always, cuda:0 when present) and model helpers."""

import numpy as np
import pytest
import warp as wp

wp.config.log_level = wp.LOG_WARNING
wp.init()

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


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
