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


def run_steps(solver, model, steps, dt, state=None, control=None, record=None):
    """Advance `steps` steps with two swapped states; `record(k, state)` after each step."""
    s0 = state or model.state()
    s1 = model.state()
    control = control or model.control()
    for k in range(steps):
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
        if record is not None:
            record(k, s0)
    return s0


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
