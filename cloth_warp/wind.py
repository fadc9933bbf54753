"""Wind: a mean velocity with optional gusts (seeded, smooth, deterministic)."""

from __future__ import annotations

import numpy as np

from .validation import LIMITS, check_direction, check_number, check_vector


class GustyWind:
    """Wind velocity w(t) [m/s]: the mean wind scaled by 1 + strength g(t) and turned about the up axis by
    turn h(t) degrees, where g and h are smooth random signals of unit RMS with time scale `period`.

    g and h are sums of four sinusoids with seeded frequencies in [0.5, 2] / period and random phases, so
    a run is reproducible and the wind is a smooth function of time (no jumps between frames).

    Args:
        mean: mean wind velocity [m/s].
        strength: gust amplitude, a fraction of the mean speed (0 = steady wind).
        period: typical time between gusts [s].
        turn: amplitude of the direction change [deg].
        up: the up direction the wind turns about.
        seed: random seed.
    """

    def __init__(self, mean=(0.0, 0.0, 0.0), *, strength: float = 0.0, period: float = 1.0, turn: float = 0.0,
                 up=(0.0, 1.0, 0.0), seed: int = 0):
        self.mean = np.asarray(check_vector("mean", mean, LIMITS["velocity"]), np.float64)
        self.strength = check_number("strength", strength, LIMITS["gust_strength"])
        self.period = check_number("period", period, LIMITS["gust_period"])
        self.turn = check_number("turn", turn, LIMITS["gust_turn"])
        self.up = check_direction("up", up)
        rng = np.random.default_rng(check_number("seed", seed, LIMITS["seed"]))
        self.frequencies = rng.uniform(0.5, 2.0, size=(2, 4)) / self.period
        """[Hz] (2, 4): the sinusoids of g (row 0) and h (row 1)."""
        self.phases = rng.uniform(0.0, 2.0 * np.pi, size=(2, 4))
        """[rad] (2, 4): their phases."""

    @property
    def steady(self) -> bool:
        return self.strength == 0.0 and self.turn == 0.0

    def _signal(self, row: int, time: float) -> float:
        # Four unit-amplitude sinusoids, scaled by sqrt(2/4) so that the RMS is 1.
        return float(np.sqrt(0.5) * np.sin(2.0 * np.pi * self.frequencies[row] * time + self.phases[row]).sum())

    def at(self, time: float) -> np.ndarray:
        """Wind velocity [m/s] at `time` [s]."""
        if self.steady:
            return self.mean.copy()
        w = self.mean * (1.0 + self.strength * self._signal(0, time))
        angle = np.radians(self.turn * self._signal(1, time))
        k = self.up
        # Rodrigues rotation of w about the up axis.
        return w * np.cos(angle) + np.cross(k, w) * np.sin(angle) + k * np.dot(k, w) * (1.0 - np.cos(angle))
