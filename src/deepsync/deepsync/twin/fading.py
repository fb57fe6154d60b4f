"""Small-scale fading of one Rayleigh tap as a sum of sinusoids (Clarke/Jakes spectrum).

    g(t) = 1/sqrt(N) * sum_n exp(j (2 pi f_max cos(alpha_n) t + phi_n))

with arrival angles alpha_n and phases phi_n drawn uniformly at random. Each term is one plane
wave with its own Doppler f_max cos(alpha_n), so every term can be handed to the front end as
a separate path. E|g|^2 = 1 over the random draws; with finite N the process is only
approximately Gaussian (N = 16 is the usual compromise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepsync.frontend.portable import phasor


@dataclass(frozen=True)
class SumOfSinusoids:
    """Random angles and phases of ``shape + (N,)`` independent sum-of-sinusoids processes."""

    cos_alpha: np.ndarray
    phase: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, shape: tuple[int, ...] = (),
             n_sinusoids: int = 16) -> SumOfSinusoids:
        if n_sinusoids < 1:
            raise ValueError(f"n_sinusoids must be >= 1, got {n_sinusoids}")
        size = (*shape, n_sinusoids)
        alpha = rng.uniform(0.0, 2.0 * np.pi, size)
        return cls(phasor(alpha).real, rng.uniform(0.0, 2.0 * np.pi, size))

    @property
    def n_sinusoids(self) -> int:
        return self.phase.shape[-1]

    def doppler_hz(self, max_doppler_hz: float) -> np.ndarray:
        """Doppler shift of every sinusoid (Hz), within +-``max_doppler_hz``."""
        return max_doppler_hz * self.cos_alpha

    def components(self, t: float, max_doppler_hz: float) -> np.ndarray:
        """Complex value of every sinusoid at time ``t`` (s); they sum to the fading gain."""
        phase = self.phase + 2.0 * np.pi * self.doppler_hz(max_doppler_hz) * t
        return phasor(phase) / np.sqrt(self.n_sinusoids)

    def gain(self, t: float, max_doppler_hz: float) -> np.ndarray:
        """Fading gain (complex amplitude, unit mean power) of each process at time ``t``."""
        return self.components(t, max_doppler_hz).sum(axis=-1)
