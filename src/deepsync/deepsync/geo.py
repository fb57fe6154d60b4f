"""WGS84 geodetic <-> ECEF <-> local ENU, the REP-103/105 ``map`` frame.

Geodetic coordinates are latitude and longitude in degrees and *ellipsoidal* height in
metres (not height above mean sea level). Geodetic <-> ECEF goes through pyproj (EPSG:4979
<-> EPSG:4978); ECEF <-> ENU is the exact rotation about the origin's tangent plane, so the
local frame is Cartesian: distances in it are true 3D distances, and "up" is the ellipsoid
normal at the origin (a point on the ellipsoid 1 km away sits ~8 cm below the plane).

All functions take scalars or arrays (broadcast against each other) and return arrays; ENU and
ECEF coordinates are stacked along a trailing axis of length 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike
from pyproj import Transformer


@lru_cache(maxsize=1)
def _geodetic_to_ecef() -> Transformer:
    return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def geodetic_to_ecef(latitude_deg: ArrayLike, longitude_deg: ArrayLike,
                     height_m: ArrayLike = 0.0) -> np.ndarray:
    """ECEF (x, y, z) in metres, shape ``broadcast(lat, lon, h).shape + (3,)``."""
    lat, lon, h = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64)
                                        for v in (latitude_deg, longitude_deg, height_m)))
    x, y, z = _geodetic_to_ecef().transform(lon, lat, h)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(ecef: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(latitude_deg, longitude_deg, height_m) of ECEF points given along a trailing axis of 3."""
    xyz = _as_points(ecef, "ecef")
    lon, lat, h = _geodetic_to_ecef().transform(xyz[..., 0], xyz[..., 1], xyz[..., 2],
                                                direction="INVERSE")
    return (np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64),
            np.asarray(h, dtype=np.float64))


def _as_points(points: ArrayLike, name: str) -> np.ndarray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim == 0 or array.shape[-1] != 3:
        raise ValueError(f"{name} must have a trailing axis of length 3, got shape {array.shape}")
    return array


def _rotate(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``points @ rotation.T`` term by term: a matrix product would go to BLAS, whose rounding
    depends on the CPU, and the simulator's geometry must not (``deepsync.frontend.portable``)."""
    return (points[..., :1] * rotation[:, 0] + points[..., 1:2] * rotation[:, 1]) + points[..., 2:] * rotation[:, 2]


@dataclass(frozen=True)
class LocalFrame:
    """East-north-up tangent plane at a WGS84 origin: the REP-105 ``map`` frame.

    ``height_m`` is the origin's ellipsoidal height; ENU ``up`` = 0 at that height.
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float = 0.0
    _origin_ecef: np.ndarray = field(init=False, repr=False, compare=False)
    _rotation: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("latitude_deg", "longitude_deg", "height_m"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)!r}")
        if not -90.0 <= self.latitude_deg <= 90.0:
            raise ValueError(f"latitude_deg {self.latitude_deg!r} is outside [-90, 90]")
        if not -180.0 <= self.longitude_deg <= 180.0:
            raise ValueError(f"longitude_deg {self.longitude_deg!r} is outside [-180, 180]")
        lat, lon = math.radians(self.latitude_deg), math.radians(self.longitude_deg)
        sin_lat, cos_lat, sin_lon, cos_lon = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        # Rows: east, north, up unit vectors in ECEF.
        rotation = np.array([
            [-sin_lon, cos_lon, 0.0],
            [-sin_lat * cos_lon, -sin_lat * sin_lon, cos_lat],
            [cos_lat * cos_lon, cos_lat * sin_lon, sin_lat],
        ])
        object.__setattr__(self, "_rotation", rotation)
        object.__setattr__(self, "_origin_ecef",
                           geodetic_to_ecef(self.latitude_deg, self.longitude_deg, self.height_m))

    def ecef_to_enu(self, ecef: ArrayLike) -> np.ndarray:
        """ENU (m) of ECEF points (trailing axis of 3)."""
        return _rotate(_as_points(ecef, "ecef") - self._origin_ecef, self._rotation)

    def enu_to_ecef(self, enu: ArrayLike) -> np.ndarray:
        """ECEF (m) of ENU points (trailing axis of 3)."""
        return _rotate(_as_points(enu, "enu"), self._rotation.T) + self._origin_ecef

    def geodetic_to_enu(self, latitude_deg: ArrayLike, longitude_deg: ArrayLike,
                        height_m: ArrayLike = 0.0) -> np.ndarray:
        """ENU (m) of geodetic points; shape ``broadcast(lat, lon, h).shape + (3,)``."""
        return self.ecef_to_enu(geodetic_to_ecef(latitude_deg, longitude_deg, height_m))

    def enu_to_geodetic(self, enu: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(latitude_deg, longitude_deg, height_m) of ENU points (trailing axis of 3)."""
        return ecef_to_geodetic(self.enu_to_ecef(enu))
