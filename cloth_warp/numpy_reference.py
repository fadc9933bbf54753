"""An independent, vectorised numpy implementation of the same forces and implicit system.

Used as the cross-check of the Warp kernels (dense implicit solve in the tests) and as the numpy
baseline of the benchmarks. It reads a :class:`~cloth_warp.model.Model`'s arrays once and works in
float64 with scatter-adds (``np.add.at``), sharing no code with the kernels.
"""

from __future__ import annotations

import numpy as np

from .topology import BUCKLING_POLY, SpringLaw

_P = np.asarray(BUCKLING_POLY)  # highest power first
_Q = np.polyint(_P)


class NumpyCloth:
    """Model arrays as numpy plus force, Jacobian and semi-implicit step routines."""

    def __init__(self, model):
        self.springs = model.spring_indices.numpy().astype(np.int64).reshape(-1, 2)
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.k = model.spring_stiffness.numpy().astype(np.float64)
        self.c = model.spring_damping.numpy().astype(np.float64)
        self.law = model.spring_law.numpy()
        self.middle = model.spring_middle.numpy().astype(np.int64)
        self.tris = model.tri_indices.numpy().astype(np.int64).reshape(-1, 3)
        self.tri_drag = model.tri_drag.numpy().astype(np.float64)
        self.tri_w = model.tri_corner_weights.numpy().astype(np.float64).reshape(-1, 3)
        self.mass = model.particle_mass.numpy().astype(np.float64)
        self.pinned = model.particle_pinned.numpy() != 0
        self.pin_k = model.particle_pin_stiffness.numpy().astype(np.float64)
        self.gravity = np.asarray(model.gravity, np.float64)
        self.global_damping = float(model.global_damping)
        self.n = len(self.mass)

    # -- forces -----------------------------------------------------------------------------
    def forces(self, x, v, pin_target, wind):
        """Total force per particle [N], shape (n, 3)."""
        x = np.asarray(x, np.float64)
        v = np.asarray(v, np.float64)
        f = self.mass[:, None] * self.gravity - self.global_damping * self.mass[:, None] * v
        i, j = self.springs[:, 0], self.springs[:, 1]
        d = x[i] - x[j]
        length = np.linalg.norm(d, axis=1)
        n = d / np.maximum(length, 1e-12)[:, None]
        lin = self.law == SpringLaw.LINEAR
        mag = np.zeros(len(length))
        mag[lin] = -(self.k[lin] * (length[lin] - self.rest[lin]) + self.c[lin] * np.sum((v[i] - v[j])[lin] * n[lin], axis=1))
        fs = mag[:, None] * n
        np.add.at(f, i[lin], fs[lin])
        np.add.at(f, j[lin], -fs[lin])
        bk = ~lin
        if bk.any():
            for idx, force in zip((i[bk], self.middle[bk], j[bk]), self.bending_forces(x, bk)):
                np.add.at(f, idx, force)
        if len(self.tris):
            a, b, c = self.tris.T
            cr = np.cross(x[b] - x[a], x[c] - x[a])
            twice = np.linalg.norm(cr, axis=1)
            w = self.tri_w
            v_rel = w[:, 0:1] * v[a] + w[:, 1:2] * v[b] + w[:, 2:3] * v[c] - np.asarray(wind, np.float64).reshape(3)
            ft = -(self.tri_drag * np.sum(cr * v_rel, axis=1) / (2.0 * np.maximum(twice, 1e-30)))[:, None] * cr
            for col, corner in enumerate((a, b, c)):
                np.add.at(f, corner, w[:, col : col + 1] * ft)
        f -= self.pin_k[:, None] * (x - pin_target)
        return f

    def bending_energy(self, x, mask=None):
        """Energies of the bend triples, E = (4 k_b / l) int_s^1 |P| (s = chord / arc)."""
        mask = self.law != SpringLaw.LINEAR if mask is None else mask
        a, m, b = self.springs[mask, 0], self.middle[mask], self.springs[mask, 1]
        arc = np.linalg.norm(x[m] - x[a], axis=1) + np.linalg.norm(x[b] - x[m], axis=1)
        s = np.minimum(np.linalg.norm(x[b] - x[a], axis=1) / arc, 1.0)
        return 4.0 * self.k[mask] / arc * (np.polyval(_Q, s) - np.polyval(_Q, 1.0))

    def bending_forces(self, x, mask):
        """Forces on (a, m, b) of the masked triples, f = f_b (grad|c| - s grad l) + (E/l) grad l."""
        a, m, b = self.springs[mask, 0], self.middle[mask], self.springs[mask, 1]
        e1, e2, c = x[m] - x[a], x[b] - x[m], x[b] - x[a]
        l1, l2, lc = (np.linalg.norm(v, axis=1) for v in (e1, e2, c))
        arc = l1 + l2
        s = np.minimum(lc / arc, 1.0)
        fb = -4.0 * self.k[mask] / arc**2 * np.polyval(_P, s)
        g = fb * s - self.bending_energy(x, mask) / arc
        u1, u2, uc = e1 / l1[:, None], e2 / l2[:, None], c / lc[:, None]
        return g[:, None] * u1 - fb[:, None] * uc, g[:, None] * (u2 - u1), fb[:, None] * uc - g[:, None] * u2

    def bending_forces_fd(self, x, eps=1e-7):
        """-dE/dx of all bend triples by central differences of the energy (an independent check)."""
        f = np.zeros_like(x)
        for p in np.unique(np.concatenate([self.springs[self.law != SpringLaw.LINEAR].ravel(), self.middle[self.middle >= 0]])):
            for d in range(3):
                xp, xm = x.copy(), x.copy()
                xp[p, d] += eps
                xm[p, d] -= eps
                f[p, d] = -(self.bending_energy(xp).sum() - self.bending_energy(xm).sum()) / (2 * eps)
        return f

    def spring_blocks(self, x):
        """K_s (PSD stiffness blocks) and D_s (damping blocks), shape (s, 3, 3) each."""
        i, j = self.springs[:, 0], self.springs[:, 1]
        d = x[i] - x[j]
        length = np.linalg.norm(d, axis=1)
        n = d / np.maximum(length, 1e-12)[:, None]
        nn = n[:, :, None] * n[:, None, :]
        eye = np.eye(3)[None]
        lin = self.law == SpringLaw.LINEAR
        K = np.zeros((len(length), 3, 3))
        t = np.maximum(0.0, 1.0 - self.rest / length)
        K[lin] = self.k[lin, None, None] * (nn[lin] + t[lin, None, None] * (eye - nn[lin]))
        D = np.where(lin[:, None, None], self.c[:, None, None] * nn, 0.0)
        return K, D

    def bending_weights(self, x):
        """sqrt(C) (1/a1, -(1/a1 + 1/a2), 1/a2) per bend triple (quadratic bending Jacobian), zeros else."""
        g = np.zeros((len(self.springs), 3))
        for s in np.flatnonzero(self.law != SpringLaw.LINEAR):
            a, b, m = self.springs[s, 0], self.springs[s, 1], self.middle[s]
            a1 = np.linalg.norm(x[m] - x[a])
            a2 = np.linalg.norm(x[b] - x[m])
            arc = a1 + a2
            chord = min(np.linalg.norm(x[b] - x[a]), arc * 0.999999)
            fb = -4.0 * self.k[s] / arc**2 * np.polyval(_P, chord / arc)
            g[s] = np.sqrt(fb * a1 * a2 / arc) * np.array([1.0 / a1, -(1.0 / a1 + 1.0 / a2), 1.0 / a2])
        return g

    # -- dense implicit system ----------------------------------------------------------------
    def implicit_system(self, x, v, pin_target, wind, dt):
        """Dense (A, b) of the linearised backward-Euler step, shape (3n, 3n) and (3n,)."""
        x = np.asarray(x, np.float64)
        v = np.asarray(v, np.float64)
        n = self.n
        K, D = self.spring_blocks(x)
        Kg = np.zeros((3 * n, 3 * n))
        Dg = np.zeros((3 * n, 3 * n))
        for s, (i, j) in enumerate(self.springs):
            for G, blk in ((Kg, K[s]), (Dg, D[s])):
                G[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += blk
                G[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += blk
                G[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] -= blk
                G[3 * j : 3 * j + 3, 3 * i : 3 * i + 3] -= blk
        g = self.bending_weights(x)
        for s in np.flatnonzero(self.law != SpringLaw.LINEAR):
            trip = (self.springs[s, 0], self.middle[s], self.springs[s, 1])
            for r, p in enumerate(trip):
                for r2, q in enumerate(trip):
                    Kg[3 * p : 3 * p + 3, 3 * q : 3 * q + 3] += g[s, r] * g[s, r2] * np.eye(3)
        for p in range(n):
            Kg[3 * p : 3 * p + 3, 3 * p : 3 * p + 3] += self.pin_k[p] * np.eye(3)
            Dg[3 * p : 3 * p + 3, 3 * p : 3 * p + 3] += self.global_damping * self.mass[p] * np.eye(3)
        for t, tri in enumerate(self.tris):
            a, b, c = x[tri]
            cr = np.cross(b - a, c - a)
            tw = np.linalg.norm(cr)
            if tw < 1e-30:
                continue
            nrm = cr / tw
            blk = self.tri_drag[t] * 0.5 * tw * np.outer(nrm, nrm)
            for cp, p in enumerate(tri):
                for cq, q in enumerate(tri):
                    Dg[3 * p : 3 * p + 3, 3 * q : 3 * q + 3] += self.tri_w[t, cp] * self.tri_w[t, cq] * blk
        M = np.kron(np.diag(self.mass), np.eye(3))
        A = M + dt * Dg + dt * dt * Kg
        f0 = self.forces(x, v, pin_target, wind).ravel()
        b = dt * (f0 - dt * Kg @ v.ravel())
        return A, b

    def solve_implicit_dense(self, x, v, pin_target, wind, dt):
        """dv of the implicit step with hard pins prescribed (dense solve on the free rows)."""
        A, b = self.implicit_system(x, v, pin_target, wind, dt)
        z = np.zeros((self.n, 3))
        z[self.pinned] = (np.asarray(pin_target)[self.pinned] - x[self.pinned]) / dt - v[self.pinned]
        free = np.repeat(~self.pinned, 3)
        zf = z.ravel()
        rhs = b[free] - A[np.ix_(free, ~free)] @ zf[~free]
        dv = zf.copy()
        dv[free] = np.linalg.solve(A[np.ix_(free, free)], rhs)
        return dv.reshape(-1, 3)

    # -- the numpy baseline of the benchmarks -------------------------------------------------
    def step_symplectic(self, x, v, pin_target, wind, dt):
        """One semi-implicit Euler step (same forces), returns (x1, v1)."""
        f = self.forces(x, v, pin_target, wind)
        v1 = v + dt * f / self.mass[:, None]
        v1[self.pinned] = (pin_target[self.pinned] - x[self.pinned]) / dt
        x1 = x + dt * v1
        x1[self.pinned] = pin_target[self.pinned]
        return x1, v1
