"""Base-station sector antenna: the TR 38.901 Table 7.3-1 element pattern, as a macro panel.

The pattern follows Table 7.3-1 in form,

    A_V(theta) = -min(12 ((theta - 90 deg - tilt) / theta_3dB)^2, SLA_V)
    A_H(phi)   = -min(12 (phi / phi_3dB)^2, A_max)
    A(theta, phi) = -min(-(A_V + A_H), A_max)

with configurable beamwidths: a typical LTE macro panel has a 65 deg horizontal and ~10 deg
vertical half-power beamwidth (the 38.901 *element* has 65/65 deg; the narrow vertical beam of a
panel is an array effect, folded here into the element form). Gains are relative to boresight
(<= 0 dB): the scenario's EIRP is specified at boresight, so the element's maximum directional
gain is already in it. The electrical downtilt moves the vertical beam peak below the horizon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from deepsync.frontend.portable import elementwise


@dataclass(frozen=True)
class SectorPattern:
    """Beam shape of a sector antenna (degrees and dB attenuations, all > 0)."""

    horizontal_beamwidth_deg: float = 65.0
    vertical_beamwidth_deg: float = 10.0
    front_back_db: float = 30.0
    side_lobe_db: float = 20.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if self.horizontal_beamwidth_deg >= 360 or self.vertical_beamwidth_deg >= 180:
            raise ValueError("beamwidths must be below 360 deg (horizontal) and 180 deg (vertical)")

    def attenuation_db(self, azimuth_off_deg: ArrayLike, elevation_off_deg: ArrayLike
                       ) -> np.ndarray:
        """Gain relative to boresight (dB, <= 0) at angles off boresight.

        ``azimuth_off_deg`` is wrapped to [-180, 180); ``elevation_off_deg`` is the zenith angle
        minus the boresight's zenith angle (positive = below the beam peak).
        """
        phi = (np.asarray(azimuth_off_deg, dtype=np.float64) + 180.0) % 360.0 - 180.0
        theta = np.asarray(elevation_off_deg, dtype=np.float64)
        horizontal = -np.minimum(12.0 * (phi / self.horizontal_beamwidth_deg) ** 2,
                                 self.front_back_db)
        vertical = -np.minimum(12.0 * (theta / self.vertical_beamwidth_deg) ** 2,
                               self.side_lobe_db)
        return -np.minimum(-(vertical + horizontal), self.front_back_db)


@dataclass(frozen=True)
class SectorAntenna:
    """A sector antenna pointed at compass ``azimuth_deg`` (clockwise from north) with
    electrical ``downtilt_deg`` (positive = below the horizon)."""

    azimuth_deg: float
    downtilt_deg: float
    pattern: SectorPattern = field(default_factory=SectorPattern)

    def gain_db(self, direction_enu: ArrayLike) -> np.ndarray:
        """Gain (dB re boresight) towards ENU direction vectors (trailing axis of 3)."""
        d = np.asarray(direction_enu, dtype=np.float64)
        bearing = np.degrees(elementwise(math.atan2, d[..., 0], d[..., 1]))
        zenith = np.degrees(elementwise(math.atan2, np.hypot(d[..., 0], d[..., 1]), d[..., 2]))
        return self.pattern.attenuation_db(bearing - self.azimuth_deg,
                                           zenith - 90.0 - self.downtilt_deg)

