"""Warp kernels and functions of cloth_warp (installed as ``cloth_warp.kernels``).

Modules are grouped by what launches together, because each module is one cold compile:

* :mod:`.forces` - force functions shared by every integrator and the explicit/RK step kernels;
* :mod:`.implicit` - Baraff-Witkin system blocks, matrix-free product, CG and Jacobi;
* :mod:`.constraints` - Provot strain limiting and animated handle targets;
* :mod:`.collide` - collider distance functions, swept contact and the friction response;
* :mod:`.broadphase` - the spatial hash grid of voxels for self-collision candidates;
* :mod:`.selfcollide` - cloth-cloth proximity, CCD and impulse distribution (Bridson et al. 2002);
* :mod:`.losses` - loss terms of differentiable rollouts (positions, Chamfer, a centroid target);
* :mod:`.diagnostics` - per-step statistics (forward only, no backward code generated).

Parameters that change between scenes are launch arguments; ``wp.constant`` is kept for true
constants. Kernels never write an argument that does not end in ``_out`` (checked by a test).
"""
