"""Warp kernels and functions of cloth_warp (installed as ``cloth_warp.kernels``).

Modules are grouped by what launches together, because each module is one cold compile:

* :mod:`.forces` - force functions shared by every integrator and the explicit/RK step kernels;
* :mod:`.implicit` - Baraff-Witkin system blocks, matrix-free product, CG and Jacobi;
* :mod:`.constraints` - Provot strain limiting and animated handle targets;
* :mod:`.collide` - collider distance functions, swept contact and the friction response;
* :mod:`.contact` - collider contacts found before the implicit solve (its constraints);
* :mod:`.broadphase` - the spatial hash grid of voxels for self-collision candidates;
* :mod:`.selfcollide` - cloth-cloth proximity, CCD and impulse distribution (Bridson et al. 2002);
* :mod:`.losses` - loss terms of differentiable rollouts (positions, Chamfer, a centroid target);
* :mod:`.diagnostics` - per-step statistics (forward only, no backward code generated).

Parameters that change between scenes are launch arguments; ``wp.constant`` is kept for true
constants. Kernels never write an argument that does not end in ``_out`` (checked by a test).
"""

import warp as wp


def contracting_cpu_flags() -> str:
    """Warp's CPU compiler flags (``wp.config.cpu_compiler_flags``, default ``-march=native``) plus
    ``-ffp-contract=fast``: a * b + c fuses into one FMA across the statements Warp's code generator
    splits expressions into, as CUDA contracts by default. The hot force and solver modules use it
    (5-6 % off the semi-implicit substep at 64^2-128^2; results change in the last bits only)."""
    base = wp.config.cpu_compiler_flags
    return f"{'-march=native' if base is None else base} -ffp-contract=fast".strip()
