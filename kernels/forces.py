"""Forces of the mass-spring cloth and the explicit / Runge-Kutta step kernels.

Notation: x, v particle positions [m] and velocities [m/s]; for a spring (i, j): d = x_i - x_j,
l = |d|, n = d / l, L its rest length; k its stiffness [N/m] (linear law) or k_b [N m^2] (buckling law),
c its damping [N s/m].

Triangle membrane elements (orthotropic StVK, physics.md section E) carry stretch and shear where a cloth
asks for them (triangle meshes by default); their notation is given above `membrane_corner_gradients`.

Plate-bending stencils (physics.md section P) carry bending where a cloth asks for them (triangle meshes by
default): a stencil s over points j with weights c_j [1/m^2] and stiffness S_s [N m^3] (A_v times the plate's
Voigt matrix) measures U = sum_j x_j c_j^T (columns: the curvature vectors u_k [1/m]) and stores
(1/2) tr(U S U^T); its force on point j is -U S c_j, its stiffness (c_i . S c_j) I.

Each spring, bend triple and triangle is evaluated once and scattered into a per-particle force array
with atomics (plain adds on the CPU backend, where this is the fastest formulation; differentiable
under wp.Tape). The integrators then read one force per particle.
"""

import warp as wp

from . import contracting_cpu_flags

wp.set_module_options({"cpu_compiler_flags": contracting_cpu_flags()})

SPRING_LINEAR = wp.constant(0)

# Choi & Ko's quartic fit of the immediate-buckling curve (physics.md 7.2).
BUCKLING_P4 = wp.constant(-11.541)
BUCKLING_P3 = wp.constant(34.193)
BUCKLING_P2 = wp.constant(-39.083)
BUCKLING_P1 = wp.constant(23.116)
BUCKLING_P0 = wp.constant(-9.713)

LENGTH_EPS = wp.constant(1.0e-9)
# The most points a plate-bending stencil has (cloth_warp.plate.STENCIL_MAX_POINTS; at most Warp's unroll limit).
PLATE_MAX_POINTS = wp.constant(16)


# P(1 - t) = R0 + R1 t + R2 t^2 + R3 t^3 + R4 t^4 (Taylor coefficients of the fit about s = 1), used to
# integrate the energy int_s^1 |P| without cancellation near the onset.
BUCKLING_R0 = wp.constant(-11.541 + 34.193 - 39.083 + 23.116 - 9.713)
BUCKLING_R1 = wp.constant(-(4.0 * -11.541 + 3.0 * 34.193 + 2.0 * -39.083 + 23.116))
BUCKLING_R2 = wp.constant(6.0 * -11.541 + 3.0 * 34.193 + -39.083)
BUCKLING_R3 = wp.constant(-(4.0 * -11.541 + 34.193))
BUCKLING_R4 = wp.constant(-11.541)


@wp.func
def buckling_curve(s: float):
    """Choi & Ko's fit P(s) of the immediate-buckling curve (negative on 0 <= s < 1), s = chord / arc."""
    return (((BUCKLING_P4 * s + BUCKLING_P3) * s + BUCKLING_P2) * s + BUCKLING_P1) * s + BUCKLING_P0


@wp.func
def buckling_curve_integral(t: float):
    """int_{1-t}^1 P(s) ds from the Taylor coefficients about s = 1 (no cancellation near the onset t = 0)."""
    return t * (BUCKLING_R0 + t * (BUCKLING_R1 * 0.5 + t * (BUCKLING_R2 * (1.0 / 3.0) + t * (BUCKLING_R3 * 0.25 + t * (BUCKLING_R4 * 0.2)))))


@wp.func
def buckling_force(chord: float, arc: float, bend_stiffness: float):
    """Choi-Ko push f_b = (4 k_b / l_arc^2) |P(chord / l_arc)| [N] (0 when the triple is straight)."""
    if chord >= arc:
        return 0.0
    return -4.0 * bend_stiffness / (arc * arc) * buckling_curve(wp.max(chord / arc, 0.0))


@wp.func
def bending_forces(xa: wp.vec3, xm: wp.vec3, xb: wp.vec3, bend_stiffness: float):
    """Forces [N] on (end a, end b, middle) of a Choi-Ko span-2 bend triple.

    Immediate buckling (Choi & Ko 2002) measured against the *current* arc length l = |e1| + |e2| of the
    two segments e1 = xm - xa, e2 = xb - xm: with chord c = xb - xa and s = |c| / l the energy is
    E(s, l) = (4 k_b / l) int_s^1 |P|, which for inextensible segments is Choi & Ko's bending energy
    (1/2) k_b l kappa^2 of the arc (polynomial fit P of their buckling curve). Its exact gradient:

        f = f_b (grad|c| - s grad l) + (E / l) grad l,   f_b = (4 k_b / l^2) |P(s)|.

    Measuring against the current arc (not the rest length) decouples bending from stretching: the
    forces vanish continuously as the triple straightens, and a small kink theta stores
    c0 k_b a1 a2 theta^2 / (2 l^3) (quadratic, so small deflections are linear).
    """
    e1 = xm - xa
    e2 = xb - xm
    c = xb - xa
    l1 = wp.length(e1)
    l2 = wp.length(e2)
    chord = wp.length(c)
    arc = l1 + l2
    if l1 < LENGTH_EPS or l2 < LENGTH_EPS or chord < LENGTH_EPS or chord >= arc:
        # straight (or degenerate): f_b = 0 and E = 0
        return wp.vec3(0.0), wp.vec3(0.0), wp.vec3(0.0)
    # f_b = s_k P(s) and E / l = s_k int_s^1 P, with the common factor s_k = -4 k_b / l^2 (4 divisions in all)
    inv_arc = 1.0 / arc
    s = chord * inv_arc
    p = buckling_curve(s)
    integral = buckling_curve_integral(1.0 - s)
    scale = -4.0 * bend_stiffness * inv_arc * inv_arc
    fb = scale * p
    g = scale * (p * s - integral)
    # g u1 - f_b uc, f_b uc - g u2, g (u2 - u1) with u = e / |e|
    fc = (fb / chord) * c
    fa = (g / l1) * e1 - fc
    f_end = fc - (g / l2) * e2
    return fa, f_end, -fa - f_end


@wp.func
def bending_stiffness_weights(xa: wp.vec3, xm: wp.vec3, xb: wp.vec3, bend_stiffness: float):
    """sqrt(C) (1/a1, -(1/a1 + 1/a2), 1/a2) of the quadratic bending model used as the Jacobian.

    Near straight the triple's energy is (C/2) |u|^2 with u = (xa - xm)/a1 + (xb - xm)/a2 (|u| ~ theta),
    C = f_b a1 a2 / l; its Hessian C w w^T (x) I is PSD and constant (Bergou et al. 2006), which keeps
    the implicit system SPD while carrying the bending stiffness.
    """
    a1 = wp.length(xm - xa)
    a2 = wp.length(xb - xm)
    chord = wp.length(xb - xa)
    if a1 < LENGTH_EPS or a2 < LENGTH_EPS:
        return wp.vec3(0.0)
    arc = a1 + a2
    fb = buckling_force(wp.min(chord, arc * 0.999999), arc, bend_stiffness)
    square = fb * a1 * a2 / arc
    if square <= 0.0:
        # a triple the fit left at zero stiffness: no square root, whose derivative at 0 is infinite (NaN adjoint)
        return wp.vec3(0.0)
    root = wp.sqrt(square)
    return root * wp.vec3(1.0 / a1, -(1.0 / a1 + 1.0 / a2), 1.0 / a2)


@wp.func
def spring_force(
    xi: wp.vec3,
    xj: wp.vec3,
    vi: wp.vec3,
    vj: wp.vec3,
    rest_length: float,
    stiffness: float,
    damping: float,
):
    """Force on particle i of a linear spring: -(k (l - L) + c (v_ij . n)) n."""
    d = xi - xj
    length2 = wp.dot(d, d)
    if length2 < LENGTH_EPS * LENGTH_EPS:  # (before the square root: its adjoint at a closed seam is 0 / 0)
        return wp.vec3(0.0)
    length = wp.sqrt(length2)
    n = d / length
    return -(stiffness * (length - rest_length) + damping * wp.dot(vi - vj, n)) * n


@wp.func
def spring_stiffness_block(xi: wp.vec3, xj: wp.vec3, rest_length: float, stiffness: float):
    """K_s = -df_i/dx_i of a linear spring, kept positive semi-definite (physics.md 3(b)):
    k [n n^T + max(0, 1 - L/l) (I - n n^T)] (transverse term dropped under compression; k I for a zero-length spring
    whose ends coincide, a welded seam's). Bend triples
    use `bending_stiffness_weights` instead."""
    d = xi - xj
    length2 = wp.dot(d, d)
    if length2 < LENGTH_EPS * LENGTH_EPS:  # (before the square root: its adjoint at a closed seam is 0 / 0)
        if rest_length <= LENGTH_EPS:  # a zero-length spring (a seam) closed: k I, its block's limit
            return stiffness * wp.identity(n=3, dtype=float)
        return wp.mat33(0.0)
    length = wp.sqrt(length2)
    n = d / length
    nn = wp.outer(n, n)
    t = wp.max(0.0, 1.0 - rest_length / length)
    return stiffness * (nn + t * (wp.identity(n=3, dtype=float) - nn))


@wp.func
def spring_damping_block(xi: wp.vec3, xj: wp.vec3, damping: float):
    """D_s = -df_i/dv_i = c n n^T of a linear spring (bend triples are undamped)."""
    d = xi - xj
    length2 = wp.dot(d, d)
    if length2 < LENGTH_EPS * LENGTH_EPS:  # (before the square root: its adjoint at a closed seam is 0 / 0)
        return wp.mat33(0.0)
    length = wp.sqrt(length2)
    n = d / length
    return damping * wp.outer(n, n)


@wp.func
def triangle_drag_force(
    xa: wp.vec3,
    xb: wp.vec3,
    xc: wp.vec3,
    va: wp.vec3,
    vb: wp.vec3,
    vc: wp.vec3,
    weights: wp.vec3,
    drag_coefficient: float,
    wind: wp.vec3,
):
    """Air drag on a triangle, f = -c_A A (n . v_rel) n, v_rel = corner-weighted mean velocity - wind.

    The total force; corner c receives weights[c] of it (the same weights average the velocity, which
    keeps the drag Jacobian symmetric).
    """
    cr = wp.cross(xb - xa, xc - xa)
    twice_area = wp.length(cr)
    if twice_area < LENGTH_EPS:
        return wp.vec3(0.0)
    v_rel = weights[0] * va + weights[1] * vb + weights[2] * vc - wind
    # A n (n . v) = (cr/2) (cr . v) / |cr|
    return -drag_coefficient * wp.dot(cr, v_rel) / (2.0 * twice_area) * cr


@wp.func
def corner_weight(i: int, a: int, b: int, weights: wp.vec3):
    """The weight of particle i among the corners (a, b, c) of a triangle."""
    if i == a:
        return weights[0]
    if i == b:
        return weights[1]
    return weights[2]


# -- triangle membrane element (docs/physics.md section E) -------------------------------------------------
# Notation: corners x_k, velocities v_k (k = 0, 1, 2); Dm^-1 the inverse rest edge matrix in the triangle's
# warp/weft frame; g_k the k-th row of [-1 -1; 1 0; 0 1] Dm^-1, so F = sum_k x_k g_k^T (3x2, columns F_w, F_f);
# Green strain e = (E_ww, E_ff, 2 E_wf) = ((F_w.F_w - 1)/2, (F_f.F_f - 1)/2, F_w.F_f); C the 3x3 Voigt matrix
# from (C_11, C_22, C_12, C_66); B_k = de/dx_k (3x3). W = A (1/2) e.C e, f_k = -A B_k^T (C e + C_d de/dt).


@wp.func
def membrane_corner_gradients(rest_inverse: wp.mat22):
    """g_0, g_1, g_2: d F / d x_k = I (x) g_k^T, from the inverse rest edge matrix Dm^-1 [1/m]."""
    g1 = wp.vec2(rest_inverse[0, 0], rest_inverse[0, 1])
    g2 = wp.vec2(rest_inverse[1, 0], rest_inverse[1, 1])
    return -(g1 + g2), g1, g2


@wp.func
def membrane_strain_jacobian(fw: wp.vec3, ff: wp.vec3, g: wp.vec2):
    """B_k = d e / d x_k of the Green strain (rows: E_ww, E_ff, 2 E_wf) for a corner with gradient g = g_k."""
    a = g[0] * fw
    b = g[1] * ff
    c = g[1] * fw + g[0] * ff
    return wp.mat33(a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])


@wp.func
def membrane_voigt(c: wp.vec4):
    """The 3x3 Voigt matrix [[C_11, C_12, 0], [C_12, C_22, 0], [0, 0, C_66]] of (C_11, C_22, C_12, C_66)."""
    return wp.mat33(c[0], c[2], 0.0, c[2], c[1], 0.0, 0.0, 0.0, c[3])


@wp.func
def membrane_deformation(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, rest_inverse: wp.mat22):
    """The columns F_w, F_f of the deformation gradient F = [x1 - x0, x2 - x0] Dm^-1."""
    d1 = x1 - x0
    d2 = x2 - x0
    fw = rest_inverse[0, 0] * d1 + rest_inverse[1, 0] * d2
    ff = rest_inverse[0, 1] * d1 + rest_inverse[1, 1] * d2
    return fw, ff


@wp.func
def membrane_strain(fw: wp.vec3, ff: wp.vec3):
    """Green strain in Voigt form e = ((F_w.F_w - 1)/2, (F_f.F_f - 1)/2, F_w.F_f) (engineering shear)."""
    return wp.vec3(0.5 * (wp.dot(fw, fw) - 1.0), 0.5 * (wp.dot(ff, ff) - 1.0), wp.dot(fw, ff))


@wp.func
def membrane_energy(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, rest_inverse: wp.mat22, area: float, stiffness: wp.vec4):
    """W = A (1/2) e . C e [J] of a triangle membrane element."""
    fw, ff = membrane_deformation(x0, x1, x2, rest_inverse)
    e = membrane_strain(fw, ff)
    return 0.5 * area * wp.dot(e, membrane_voigt(stiffness) * e)


@wp.func
def membrane_forces(
    x0: wp.vec3,
    x1: wp.vec3,
    x2: wp.vec3,
    v0: wp.vec3,
    v1: wp.vec3,
    v2: wp.vec3,
    rest_inverse: wp.mat22,
    area: float,
    stiffness: wp.vec4,
    damping: wp.vec4,
):
    """Forces [N] on the corners of a membrane element: f_k = -A B_k^T (C e + C_d de/dt), de/dt = sum_l B_l v_l
    (orthotropic StVK membrane with Kelvin-Voigt damping C_d = tau C)."""
    fw, ff = membrane_deformation(x0, x1, x2, rest_inverse)
    g0, g1, g2 = membrane_corner_gradients(rest_inverse)
    b0 = membrane_strain_jacobian(fw, ff, g0)
    b1 = membrane_strain_jacobian(fw, ff, g1)
    b2 = membrane_strain_jacobian(fw, ff, g2)
    rate = b0 * v0 + b1 * v1 + b2 * v2
    stress = area * (membrane_voigt(stiffness) * membrane_strain(fw, ff) + membrane_voigt(damping) * rate)
    return -(wp.transpose(b0) * stress), -(wp.transpose(b1) * stress), -(wp.transpose(b2) * stress)


@wp.func
def positive_stress(s: wp.vec3):
    """The positive part of the symmetric 2x2 stress [[s_0, s_2], [s_2, s_1]] (negative eigenvalues set to 0),
    returned as (s_ww, s_ff, s_wf). The square root is taken only where the eigenvalues have opposite signs
    (then it is > 0), so the tape's adjoint stays finite."""
    det = s[0] * s[1] - s[2] * s[2]
    tr = s[0] + s[1]
    if det >= 0.0:
        if tr >= 0.0:
            return s
        return wp.vec3(0.0)
    half = 0.5 * tr
    r = wp.sqrt(half * half - det)
    top = half + r
    low = half - r
    # S+ = top (S - low I) / (top - low)
    scale = top / (2.0 * r)
    return wp.vec3(scale * (s[0] - low), scale * (s[1] - low), scale * s[2])


@wp.func
def membrane_geometric_weights(g0: wp.vec2, g1: wp.vec2, g2: wp.vec2, s: wp.vec3):
    """The corner matrix G_kl = g_k^T S g_l of the geometric stiffness (G (x) I_3) for the 2x2 stress s."""
    sg0 = wp.vec2(s[0] * g0[0] + s[2] * g0[1], s[2] * g0[0] + s[1] * g0[1])
    sg1 = wp.vec2(s[0] * g1[0] + s[2] * g1[1], s[2] * g1[0] + s[1] * g1[1])
    sg2 = wp.vec2(s[0] * g2[0] + s[2] * g2[1], s[2] * g2[0] + s[1] * g2[1])
    return wp.mat33(
        wp.dot(g0, sg0), wp.dot(g0, sg1), wp.dot(g0, sg2),
        wp.dot(g1, sg0), wp.dot(g1, sg1), wp.dot(g1, sg2),
        wp.dot(g2, sg0), wp.dot(g2, sg1), wp.dot(g2, sg2),
    )


@wp.func
def membrane_system(
    x0: wp.vec3,
    x1: wp.vec3,
    x2: wp.vec3,
    rest_inverse: wp.mat22,
    area: float,
    stiffness: wp.vec4,
    damping: wp.vec4,
    stiffness_scale: float,
    damping_scale: float,
):
    """The pieces of an element's matrix a K + b D (a = `stiffness_scale`, b = `damping_scale`), with
    K = A B^T C B + A G(S+) (x) I (Gauss-Newton plus the geometric stiffness of the positive part S+ of the
    stress S = C e: positive semi-definite, and the exact Hessian wherever S >= 0) and D = A B^T C_d B:
    returns B_0, B_1, B_2, the Voigt matrix A (a C + b C_d) and the corner matrix a A G(S+)."""
    fw, ff = membrane_deformation(x0, x1, x2, rest_inverse)
    g0, g1, g2 = membrane_corner_gradients(rest_inverse)
    b0 = membrane_strain_jacobian(fw, ff, g0)
    b1 = membrane_strain_jacobian(fw, ff, g1)
    b2 = membrane_strain_jacobian(fw, ff, g2)
    c = membrane_voigt(stiffness)
    stress = positive_stress(c * membrane_strain(fw, ff))
    voigt = area * (stiffness_scale * c + damping_scale * membrane_voigt(damping))
    geometric = (stiffness_scale * area) * membrane_geometric_weights(g0, g1, g2, stress)
    return b0, b1, b2, voigt, geometric


@wp.func
def membrane_product(b0: wp.mat33, b1: wp.mat33, b2: wp.mat33, voigt: wp.mat33, geometric: wp.mat33, p0: wp.vec3, p1: wp.vec3,
                     p2: wp.vec3):
    """y_k = B_k^T V (sum_l B_l p_l) + sum_l G_kl p_l: the element matrix of `membrane_system` times (p_0, p_1, p_2)."""
    t = voigt * (b0 * p0 + b1 * p1 + b2 * p2)
    y0 = wp.transpose(b0) * t + geometric[0, 0] * p0 + geometric[0, 1] * p1 + geometric[0, 2] * p2
    y1 = wp.transpose(b1) * t + geometric[1, 0] * p0 + geometric[1, 1] * p1 + geometric[1, 2] * p2
    y2 = wp.transpose(b2) * t + geometric[2, 0] * p0 + geometric[2, 1] * p1 + geometric[2, 2] * p2
    return y0, y1, y2


@wp.kernel
def eval_spring_forces(
    # Model
    spring_ends: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    # State
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # outputs (zeroed by the caller)
    force_out: wp.array(dtype=wp.vec3),
):
    """Linear springs (the first `linear_spring_count` springs): scatter +-f to both ends."""
    s = wp.tid()
    e = spring_ends[s]
    f = spring_force(x[e[0]], x[e[1]], v[e[0]], v[e[1]], spring_rest_length[s], spring_stiffness[s], spring_damping[s])
    wp.atomic_add(force_out, e[0], f)
    wp.atomic_sub(force_out, e[1], f)


@wp.kernel
def eval_bending_forces(
    # Model
    bend_triples: wp.array(dtype=wp.vec3i),
    spring_stiffness: wp.array(dtype=float),
    first: int,
    # State
    x: wp.array(dtype=wp.vec3),
    # outputs (zeroed by the caller)
    force_out: wp.array(dtype=wp.vec3),
):
    """Choi-Ko bend triples (end a, middle, end b; springs `first` onwards): scatter the three forces."""
    q = wp.tid()
    t = bend_triples[q]
    bend_stiffness = spring_stiffness[q + first]
    fa, fb, fm = bending_forces(x[t[0]], x[t[1]], x[t[2]], bend_stiffness)
    if bend_stiffness != 0.0 and wp.length_sq(fa) + wp.length_sq(fb) == 0.0:
        # straight (most triples of a smooth cloth in float32): nothing to scatter, and no gradient to pass
        # (with k_b = 0 the scatter still runs, so d f / d k_b reaches the tape)
        return
    wp.atomic_add(force_out, t[0], fa)
    wp.atomic_add(force_out, t[2], fb)
    wp.atomic_add(force_out, t[1], fm)


@wp.kernel
def eval_membrane_forces(
    # Model
    membrane_vertices: wp.array(dtype=wp.vec3i),
    membrane_rest_inverse: wp.array(dtype=wp.mat22),
    membrane_rest_area: wp.array(dtype=float),
    membrane_stiffness: wp.array(dtype=wp.vec4),
    membrane_damping: wp.array(dtype=wp.vec4),
    # State
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # outputs (zeroed by the caller)
    force_out: wp.array(dtype=wp.vec3),
):
    """Triangle membrane elements: scatter f_k = -A B_k^T (C e + C_d de/dt) to the three corners."""
    e = wp.tid()
    c = membrane_vertices[e]
    f0, f1, f2 = membrane_forces(x[c[0]], x[c[1]], x[c[2]], v[c[0]], v[c[1]], v[c[2]], membrane_rest_inverse[e],
                                 membrane_rest_area[e], membrane_stiffness[e], membrane_damping[e])
    wp.atomic_add(force_out, c[0], f0)
    wp.atomic_add(force_out, c[1], f1)
    wp.atomic_add(force_out, c[2], f2)


@wp.func
def plate_curvature(plate_points: wp.array(dtype=wp.int32), plate_weights: wp.array(dtype=wp.vec3), start: int, end: int,
                    x: wp.array(dtype=wp.vec3)):
    """U = sum_j x_j c_j^T over the stencil's entries [start, end): column k is the curvature vector u_k [1/m]
    (x: positions [m], or any per-particle vector for a product with the stencil's stiffness). Summed as
    sum_j (x_j - x_v) c_j^T (the same, as sum_j c_j = 0; x_v the stencil's vertex, its first point), so float32
    round-off scales with the stencil's size, not with the distance from the origin."""
    u = wp.mat33(0.0)
    origin = x[plate_points[start]]
    # a constant trip count (unrolled): a local summed in a dynamic loop would not be differentiable
    for j in range(1, PLATE_MAX_POINTS):
        k = start + j
        if k < end:
            u += wp.outer(x[plate_points[k]] - origin, plate_weights[k])
    return u


@wp.func
def add_plate_product(s: int, plate_offsets: wp.array(dtype=wp.int32), plate_points: wp.array(dtype=wp.int32),
                      plate_weights: wp.array(dtype=wp.vec3), plate_stiffness: wp.array(dtype=wp.mat33), p: wp.array(dtype=wp.vec3),
                      scale: float, product_out: wp.array(dtype=wp.vec3)):
    """Stencil s's part of scale K p added to its points (`scatter_plate_product`)."""
    start = plate_offsets[s]
    end = plate_offsets[s + 1]
    t = scale * plate_curvature(plate_points, plate_weights, start, end, p) * plate_stiffness[s]
    for k in range(start, end):
        wp.atomic_add(product_out, plate_points[k], t * plate_weights[k])


@wp.kernel
def scatter_plate_product(
    # Model
    plate_offsets: wp.array(dtype=wp.int32),
    plate_points: wp.array(dtype=wp.int32),
    plate_weights: wp.array(dtype=wp.vec3),
    plate_stiffness: wp.array(dtype=wp.mat33),
    # a per-particle vector and its factor
    p: wp.array(dtype=wp.vec3),
    scale: float,
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """scale K p, scattered: scale U(p) S c_j to each point j of each stencil. The energy is quadratic, so with p the
    positions and scale -1 these are the stencils' forces f = -K x; the implicit solver uses scale h^2."""
    add_plate_product(wp.tid(), plate_offsets, plate_points, plate_weights, plate_stiffness, p, scale, product_out)


@wp.kernel
def eval_drag_forces(
    # Model
    tri_vertices: wp.array(dtype=wp.vec3i),
    tri_drag: wp.array(dtype=float),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    # State
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # Control
    wind: wp.array(dtype=wp.vec3),
    # outputs (zeroed by the caller)
    force_out: wp.array(dtype=wp.vec3),
):
    """Air drag with wind per triangle, split over its corners by the drag weights."""
    t = wp.tid()
    c = tri_vertices[t]
    w = tri_corner_weights[t]
    f = triangle_drag_force(x[c[0]], x[c[1]], x[c[2]], v[c[0]], v[c[1]], v[c[2]], w, tri_drag[t], wind[0])
    wp.atomic_add(force_out, c[0], w[0] * f)
    wp.atomic_add(force_out, c[1], w[1] * f)
    wp.atomic_add(force_out, c[2], w[2] * f)


@wp.func
def total_force(
    i: int,
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    element_force: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
):
    """Total force on particle i [N]: springs, bending and drag (scattered), gravity, soft pin, global damping."""
    m = particle_mass[i]
    f = element_force[i] + m * gravity - global_damping * m * v[i]
    kp = particle_pin_stiffness[i]
    if kp > 0.0:
        f -= kp * (x[i] - pin_target[i])
    return f


@wp.kernel
def integrate_euler(
    # Model
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    element_force: wp.array(dtype=wp.vec3),
    # State in
    x_in: wp.array(dtype=wp.vec3),
    v_in: wp.array(dtype=wp.vec3),
    # Control
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
    dt: float,
    symplectic: int,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """One Euler step: explicit (x += h v; v += h a) or symplectic (v += h a; x += h v_new)."""
    i = wp.tid()
    x0 = x_in[i]
    if particle_pinned[i] != 0:
        target = pin_target[i]
        x_out[i] = target
        v_out[i] = (target - x0) / dt
        return
    f = total_force(i, particle_mass, particle_pin_stiffness, element_force, x_in, v_in, pin_target, gravity, global_damping)
    v0 = v_in[i]
    v1 = v0 + (dt / particle_mass[i]) * f
    if symplectic != 0:
        x_out[i] = x0 + dt * v1
    else:
        x_out[i] = x0 + dt * v0
    v_out[i] = v1


@wp.kernel
def eval_rk_stage(
    # Model
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    element_force: wp.array(dtype=wp.vec3),
    # State: step start and the stage's evaluation point
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    x_eval: wp.array(dtype=wp.vec3),
    v_eval: wp.array(dtype=wp.vec3),
    # Control
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
    dt: float,
    next_coeff: float,
    # outputs
    dxdt_out: wp.array(dtype=wp.vec3),
    dvdt_out: wp.array(dtype=wp.vec3),
    x_next_out: wp.array(dtype=wp.vec3),
    v_next_out: wp.array(dtype=wp.vec3),
):
    """Runge-Kutta stage: k = (v, a)(y_eval); next evaluation point y0 + next_coeff * k."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        # Pinned particles move with the constant velocity that lands them on their target.
        vp = (pin_target[i] - x0[i]) / dt
        dxdt_out[i] = vp
        dvdt_out[i] = wp.vec3(0.0)
        x_next_out[i] = x0[i] + next_coeff * vp
        v_next_out[i] = vp
        return
    f = total_force(i, particle_mass, particle_pin_stiffness, element_force, x_eval, v_eval, pin_target, gravity, global_damping)
    a = f / particle_mass[i]
    ve = v_eval[i]
    dxdt_out[i] = ve
    dvdt_out[i] = a
    x_next_out[i] = x0[i] + next_coeff * ve
    v_next_out[i] = v0[i] + next_coeff * a


@wp.kernel
def combine_rk_stages(
    particle_pinned: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dx1: wp.array(dtype=wp.vec3),
    dv1: wp.array(dtype=wp.vec3),
    dx2: wp.array(dtype=wp.vec3),
    dv2: wp.array(dtype=wp.vec3),
    dx3: wp.array(dtype=wp.vec3),
    dv3: wp.array(dtype=wp.vec3),
    dx4: wp.array(dtype=wp.vec3),
    dv4: wp.array(dtype=wp.vec3),
    pin_target: wp.array(dtype=wp.vec3),
    w1: float,
    w2: float,
    w3: float,
    w4: float,
    dt: float,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """y1 = y0 + h (w1 k1 + w2 k2 + w3 k3 + w4 k4); pinned particles land exactly on their target."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        target = pin_target[i]
        x_out[i] = target
        v_out[i] = (target - x0[i]) / dt
        return
    x_out[i] = x0[i] + dt * (w1 * dx1[i] + w2 * dx2[i] + w3 * dx3[i] + w4 * dx4[i])
    v_out[i] = v0[i] + dt * (w1 * dv1[i] + w2 * dv2[i] + w3 * dv3[i] + w4 * dv4[i])


@wp.kernel
def eval_particle_forces(
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    element_force: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
    # outputs
    force_out: wp.array(dtype=wp.vec3),
):
    """Total force on every particle (for tests, the numpy cross-check and diagnostics)."""
    i = wp.tid()
    force_out[i] = total_force(i, particle_mass, particle_pin_stiffness, element_force, x, v, pin_target, gravity, global_damping)
