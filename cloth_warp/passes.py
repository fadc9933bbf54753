"""The stages of a step after the integrator, behind one interface, and the factory that builds them.

A step is data: the integrator proposes an end state from the start state, then the solver runs its
passes in order (strain limiting, sewing, colliders, self-collision), each
turning a proposed (x_end, v_end) into a corrected (x_out, v_out) given the step's start positions. With
a corrector (the strain limiter) and contact passes both on, the sequence repeats `rounds` times so that
the last word is the contacts'. Every pass:

* ``begin_step()`` once per step before its first round, ``end_step()`` after the last (``discard_step()``
  takes a rejected adaptive step back out of its record);
* ``apply(x_start, x_end, v_end, control, dt, x_out, v_out)``;
* keeps typed counters on the device, read once per frame (``reset_report()`` / ``read_report()``);
* names the Warp modules it launches (``kernel_modules``) and says whether its forward ``apply`` can be
  recorded in a graph (``capturable``: no host reads, no host-sized buffers inside a step; a pass with a
  separate recordable path takes it after ``set_recordable(True)``);
* may ask for its frame again (``needs_rerun(report)``: a capturable path whose fixed buffers overflowed, or
  a step only its host path resolves): the Simulator then restores the frame's start, calls every pass's
  ``begin_rerun()`` (what it carries from step to step back to the frame's start, as ``reset_report()`` saved
  it) and the asking ones' ``prepare_rerun(report)`` (grow buffers, switch to the host path; True when arrays
  were replaced, so a recorded frame is recorded again), runs the frame eagerly and calls ``end_rerun()``;
* refreshes what it derived from the model on ``notify_model_changed(flags)`` and carries state from step to
  step only through ``checkpoint_state()`` / ``restore_state()`` (under its ``checkpoint_key``).
"""

from __future__ import annotations

from .model import Control, Model


class StepPass:
    """Base of the passes (see the module). Subclasses set `name` and implement :meth:`apply`."""

    name = "pass"
    checkpoint_key = ""
    """Prefix of this pass's checkpoint entries ("" when it carries nothing from step to step)."""
    corrector = False
    """A pass that may push cloth into what the contact passes resolve (the strain limiter): rounds repeat."""
    device_loops = False
    """Its apply loops on the device (wp.capture_while): capturing it on CUDA needs conditional graph nodes."""

    @property
    def kernel_modules(self) -> tuple:
        return ()

    @property
    def capturable(self) -> bool:
        return True

    def begin_step(self) -> None:
        pass

    def end_step(self) -> None:
        pass

    def discard_step(self) -> None:
        pass

    def apply(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out) -> None:
        raise NotImplementedError

    def reset_report(self) -> None:
        pass

    def read_report(self):
        return None

    def record_arrays(self) -> list:
        """(owner, attribute) of each device array :meth:`read_report` reads, for the frame's one-read record
        (:class:`~cloth_warp.records.FrameRecord`); read them with :func:`~cloth_warp.records.record_values`."""
        return []

    def set_recordable(self, on: bool) -> None:
        """Take the path that can be recorded in a graph (`on`), else the host path (the default: a step called
        directly, outside a Simulator, then never needs a re-run). The Simulator turns it on for its fixed-step
        frames, captured or not, so both run the same kernels."""

    def needs_rerun(self, report) -> bool:
        return False

    def begin_rerun(self) -> None:
        """The frame runs again (every pass, before the asking ones' :meth:`prepare_rerun`): restore what it carries
        from step to step to where the frame started it."""

    def prepare_rerun(self, report) -> bool:
        return False

    def end_rerun(self) -> None:
        pass

    def notify_model_changed(self, flags: int) -> None:
        pass

    def checkpoint_state(self) -> dict:
        return {}

    def restore_state(self, state: dict) -> None:
        pass


def build_passes(model: Model, *, strain_limit: float | None = 0.1, strain_limit_iterations: int | None = None,
                 strain_limit_tolerance: float | None = 1.0e-3, collisions: bool = True) -> list[StepPass]:
    """The passes a model needs, in the order a step runs them: Provot strain limiting (when `strain_limit`
    and the model has limited springs), sewing (when it has seams), then the colliders (when it has any) and
    self-collision (when on)."""
    from .collision import ColliderPass, SelfCollisionPass, WorldSelfCollisionPass
    from .sewing import SewingPass
    from .solvers.strain_limit import DEFAULT_SWEEPS, StrainLimiter

    out: list[StepPass] = []
    if strain_limit:
        limiter = StrainLimiter(model, strain_limit, DEFAULT_SWEEPS if strain_limit_iterations is None else strain_limit_iterations,
                                tolerance=strain_limit_tolerance)
        if limiter.active:
            out.append(limiter)
    sewing = SewingPass(model)
    if sewing.active:
        if out:
            out[0].weld_sewn_points(sewing.weld.weld_distance)  # the limiter keeps the welded points together
        out.append(sewing)
    if collisions and model.collider_count:
        out.append(ColliderPass(model))
    if collisions and model.self_collision and model.tri_count:
        out.append(WorldSelfCollisionPass(model) if model.world_count > 1 else SelfCollisionPass(model))
    return out
