"""Analytic and numerically exact references (pure numpy): catenaries and the heavy elastica."""

import math

import numpy as np


def bisect(f, lo, hi, tol=1e-15, iters=200):
    """Root of a monotone f on [lo, hi] by bisection (f(lo), f(hi) of opposite sign)."""
    flo = f(lo)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        fm = f(mid)
        if (fm > 0) == (flo > 0):
            lo, flo = mid, fm
        else:
            hi = mid
        if hi - lo < tol * max(1.0, abs(mid)):
            break
    return 0.5 * (lo + hi)


def discrete_chain(n: int, span: float, length: float, mass: float, stiffness: float, g: float = 9.81):
    """Static equilibrium of n springs (rest length length/n, stiffness k), n-1 interior nodes of mass
    mass/n, ends pinned at equal height `span` apart (physics.md 1(c)). Returns (H, node x, node z)."""
    l0 = length / n
    m = mass / n
    j = np.arange(1, n + 1)
    v = (n + 1 - 2 * j) * m * g / 2.0  # vertical force in spring j

    def span_error(h):
        t = np.sqrt(h * h + v * v)
        return float(np.sum((l0 + t / stiffness) * h / t)) - span

    h = bisect(span_error, 1e-12, 1e12)
    t = np.sqrt(h * h + v * v)
    seg = l0 + t / stiffness
    x = np.concatenate([[0.0], np.cumsum(seg * h / t)])
    z = np.concatenate([[0.0], np.cumsum(-seg * v / t)])
    return h, x, z


def elastic_catenary_sag(span: float, length: float, weight_per_length: float, ea: float) -> float:
    """Mid-span sag of the elastic catenary (Irvine 1981), q per unstretched length."""
    q = weight_per_length

    def span_error(h):
        return h * length / ea + 2 * h / q * math.asinh(q * length / (2 * h)) - span

    h = bisect(span_error, 1e-9, 1e9)
    return q * length**2 / (8 * ea) + h / q * (math.sqrt(1 + (q * length / (2 * h)) ** 2) - 1)


# Heavy elastica, clamped-free strip under its own weight (physics.md 1(a), [computed] table):
# alpha = q L^3 / B -> tip deflection delta / L.
ELASTICA_DEFLECTION = {
    0.5: 0.06231, 1.0: 0.12347, 2.0: 0.23851, 3.0: 0.33965, 4.0: 0.42516, 5.0: 0.49591,
    6.0: 0.55392, 7.0: 0.60148, 8.0: 0.64063, 9.0: 0.67308, 10.0: 0.70020,
}


def elastica_deflection(alpha: float, nodes: int = 1000) -> float:
    """Tip deflection delta / L of the heavy elastica at alpha = q L^3 / B (physics.md 1(a)): shooting on
    phi'' = -alpha (1 - s) cos phi, phi(0) = 0, phi'(1) = 0 with RK4; matches ELASTICA_DEFLECTION to 1e-5."""
    h = 1.0 / nodes

    def shoot(slope):
        phi, dphi, z = 0.0, slope, 0.0
        for k in range(nodes):
            s = k * h

            def f(s_, p, dp):
                return dp, -alpha * (1.0 - s_) * math.cos(p)

            k1 = f(s, phi, dphi)
            k2 = f(s + h / 2, phi + h / 2 * k1[0], dphi + h / 2 * k1[1])
            k3 = f(s + h / 2, phi + h / 2 * k2[0], dphi + h / 2 * k2[1])
            k4 = f(s + h, phi + h * k3[0], dphi + h * k3[1])
            z += h / 6 * (math.sin(phi) + 2 * math.sin(phi + h / 2 * k1[0]) + 2 * math.sin(phi + h / 2 * k2[0]) + math.sin(phi + h * k3[0]))
            phi += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            dphi += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        return dphi, z

    slope = bisect(lambda c: shoot(c)[0], 0.0, alpha, tol=1e-10, iters=60)
    return shoot(slope)[1]
