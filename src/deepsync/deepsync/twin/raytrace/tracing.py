"""Tracing paths with Sionna RT: one antenna position to many receiver positions at one carrier,
cached on disk.

Both ends are single isotropic, vertically polarised antennas: a sector's pattern is applied to
each path's departure direction afterwards (``RayTracedChannel``), which for a vertically
polarised element is exactly what Sionna's own pattern does (a real gain on the theta field
component), and lets one trace serve all the sectors of a site.

The cache key is a SHA-256 of the scene (its files' contents and the Sionna version), the map
frame, the antenna and receiver positions (in scene coordinates, as float64 bytes), the carrier
and the solver settings: a second run loads the arrays, any changed input traces anew. A cache
file that cannot be read is traced again; one that cannot be written is a warning.
"""

from __future__ import annotations

import enum
import hashlib
import os
import re
import tempfile
import warnings
import zipfile
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from deepsync.twin.raytrace.backend import sionna_rt
from deepsync.twin.raytrace.scenes import RayScene

RECEIVERS_PER_SOLVE = 250  # receivers added to the scene for one solver call (bounds its memory)
CACHE_FORMAT = 1  # bump when TracedPaths' arrays change meaning
# the share S of a wall's reflected field amplitude that scatters diffusely (sqrt(1 - S^2) stays
# specular): measured building walls lie at 0.2-0.5 (Degli-Esposti et al., IEEE TAP 55(1), 2007)
DIFFUSE_SCATTERING = 0.3


class Interaction(enum.IntFlag):
    """What a path met on its way, as Sionna RT numbers it (sionna.rt.constants.InteractionType)."""

    SPECULAR = 1
    DIFFUSE = 2
    REFRACTION = 4
    DIFFRACTION = 8


@dataclass(frozen=True)
class TraceSettings:
    """Sionna's path solver settings (docs/raytracing.md says why these defaults).

    ``max_depth``: most interactions per path (a pass through a wall is one, a building two);
    ``diffraction``: first-order edge diffraction (around corners, over roofs); ``diffuse``:
    diffuse scattering off every surface, with scattering coefficient DIFFUSE_SCATTERING (the
    ITU materials Sionna loads have none, so without it nothing scatters); ``refraction``: paths
    through walls; ``samples_per_source``: rays shot per antenna; ``seed``: their draw.
    """

    max_depth: int = 3
    diffraction: bool = True
    diffuse: bool = False
    refraction: bool = True
    samples_per_source: int = 1_000_000
    seed: int = 42


@dataclass(frozen=True)
class TracedPaths:
    """Paths from one antenna to N receiver positions at one carrier, padded to P paths each.

    All positions and directions are in the map frame (ENU, m):

    transmitter_enu: (3,)      the antenna
    receivers_enu:   (N, 3)    the receiver positions
    valid:           (N, P)    which entries are paths
    delays_s:        (N, P)    propagation delay
    gains:           (N, P)    complex amplitude gain between isotropic antennas, carrier phase
                               exp(-j 2 pi f tau) included: path loss and every interaction
    los:             (N, P)    the path is the direct line of sight
    interactions:    (N, P)    the Interaction flags of everything the path met (0: LOS)
    departure_enu:   (N, P, 3) unit vector along which the path leaves the antenna
    arrival_enu:     (N, P, 3) unit vector from the receiver towards where the path comes from
    """

    carrier_hz: float
    transmitter_enu: np.ndarray
    receivers_enu: np.ndarray
    valid: np.ndarray
    delays_s: np.ndarray
    gains: np.ndarray
    los: np.ndarray
    interactions: np.ndarray
    departure_enu: np.ndarray
    arrival_enu: np.ndarray

    def __len__(self) -> int:
        return len(self.receivers_enu)

    def at(self, index: int) -> dict[str, np.ndarray]:
        """The valid paths of receiver position ``index``, earliest first: the arrays above
        without the padding (``delays_s``, ``gains``, ``los``, ``interactions``,
        ``departure_enu``, ``arrival_enu``)."""
        keep = self.path_order(index)
        return {name: getattr(self, name)[index, keep]
                for name in ("delays_s", "gains", "los", "interactions", "departure_enu", "arrival_enu")}

    def path_order(self, index: int) -> np.ndarray:
        """Indices of receiver position ``index``'s valid paths, earliest first."""
        keep = np.flatnonzero(self.valid[index])
        return keep[np.argsort(self.delays_s[index, keep], kind="stable")]

    def save(self, path: Path) -> None:
        """Write the arrays to ``path`` (.npz) atomically."""
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz.part")
        try:
            with os.fdopen(handle, "wb") as out:
                np.savez(out, format=CACHE_FORMAT, **{f.name: getattr(self, f.name) for f in fields(self)})
            os.replace(temporary, path)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: Path) -> TracedPaths:
        with np.load(path) as data:
            if int(data["format"]) != CACHE_FORMAT:
                raise ValueError(f"{path}: cache format {int(data['format'])}, expected {CACHE_FORMAT}")
            values = {f.name: data[f.name] for f in fields(cls)}
        values["carrier_hz"] = float(values["carrier_hz"])
        return cls(**values)


def cache_key(scene: RayScene, transmitter_enu: np.ndarray, carrier_hz: float,
              receivers_enu: np.ndarray, settings: TraceSettings) -> str:
    """The hex SHA-256 naming a trace's cache file (see the module docstring); the map frame is
    in it because the stored positions and directions are in that frame."""
    frame = scene.map_frame
    digest = hashlib.sha256(f"{CACHE_FORMAT} {scene.digest} {carrier_hz!r} {asdict(settings)!r} "
                            f"{DIFFUSE_SCATTERING!r} {frame.latitude_deg!r} {frame.longitude_deg!r} "
                            f"{frame.height_m!r}".encode())
    digest.update(np.ascontiguousarray(scene.to_scene(transmitter_enu), dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(scene.to_scene(receivers_enu), dtype="<f8").tobytes())
    return digest.hexdigest()


def trace_paths(scene: RayScene, transmitter_enu: ArrayLike, carrier_hz: float,
                receivers_enu: ArrayLike, settings: TraceSettings = TraceSettings(),
                cache_dir: str | Path | None = None, progress: object | None = None) -> TracedPaths:
    """Paths from an antenna at ``transmitter_enu`` to every receiver position (N, 3) of
    ``receivers_enu`` (map frame) at ``carrier_hz``; loaded from ``cache_dir`` when traced
    before with the same inputs, and stored there otherwise. ``progress`` (a tqdm bar) is
    advanced by one per receiver position traced."""
    transmitter = np.asarray(transmitter_enu, dtype=np.float64).reshape(3)
    receivers = np.asarray(receivers_enu, dtype=np.float64).reshape(-1, 3)
    if not (np.all(np.isfinite(transmitter)) and np.all(np.isfinite(receivers)) and len(receivers)):
        raise ValueError("trace_paths needs a finite antenna position and at least one finite receiver position")
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / "paths" / f"{cache_key(scene, transmitter, carrier_hz, receivers, settings)}.npz"
        if path.is_file():
            try:
                cached = TracedPaths.load(path)
            except (OSError, ValueError, KeyError, zipfile.BadZipFile):
                cached = None  # damaged or of another format: traced again and replaced below
            if cached is not None:
                if progress is not None:
                    progress.update(len(receivers))
                return cached
    traced = _trace(scene, transmitter, float(carrier_hz), receivers, settings, progress)
    if path is not None:
        try:
            traced.save(path)
        except OSError as error:  # the trace itself is good: use it, and say why it is not kept
            warnings.warn(f"ray-tracing cache: cannot write {path} ({error.strerror or error}); "
                          f"the next run traces again", stacklevel=2)
    return traced


_LOADED: dict[str, object] = {}  # scene digest -> loaded sionna Scene (loading Munich takes a second)


def _trace(scene: RayScene, transmitter: np.ndarray, carrier_hz: float, receivers: np.ndarray,
           settings: TraceSettings, progress: object | None) -> TracedPaths:
    rt = sionna_rt()
    import mitsuba as mi  # noqa: PLC0415 (comes with sionna-rt)

    sionna_scene = _LOADED.get(scene.digest)
    if sionna_scene is None:
        # Sionna merges the shapes of one material into one object: those to remove are kept apart
        keep_apart = f"^(mesh-)?({'|'.join(map(re.escape, scene.removed))})$" if scene.removed else None
        sionna_scene = rt.load_scene(str(scene.xml_path), merge_shapes_exclude_regex=keep_apart)
        if scene.removed:
            absent = [name for name in scene.removed if name not in sionna_scene.objects]
            if absent:  # Scene.edit passes over a name it does not know
                raise ValueError(f"scene {scene.name!r}: no object named {', '.join(map(repr, absent))} to remove")
            sionna_scene.edit(remove=list(scene.removed))
        _LOADED[scene.digest] = sionna_scene
    sionna_scene.frequency = carrier_hz
    for material in sionna_scene.radio_materials.values():
        material.scattering_coefficient = DIFFUSE_SCATTERING if settings.diffuse else 0.0
    sionna_scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sionna_scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    for name in list(sionna_scene.transmitters) + list(sionna_scene.receivers):
        sionna_scene.remove(name)
    sionna_scene.add(rt.Transmitter(name="tx", position=mi.Point3f(*scene.to_scene(transmitter).tolist())))
    solver = rt.PathSolver()
    chunks = []
    for start in range(0, len(receivers), RECEIVERS_PER_SOLVE):
        block = scene.to_scene(receivers[start : start + RECEIVERS_PER_SOLVE])
        names = [f"rx{i}" for i in range(len(block))]
        for name, point in zip(names, block.tolist()):
            sionna_scene.add(rt.Receiver(name=name, position=mi.Point3f(*point)))
        paths = solver(sionna_scene, max_depth=settings.max_depth, los=True,
                       specular_reflection=settings.max_depth > 0, diffuse_reflection=settings.diffuse,
                       refraction=settings.refraction, diffraction=settings.diffraction,
                       samples_per_src=settings.samples_per_source, seed=settings.seed)
        chunks.append(_arrays(paths, carrier_hz, scene))
        for name in names:
            sionna_scene.remove(name)
        if progress is not None:
            progress.update(len(block))
    width = max(chunk["valid"].shape[1] for chunk in chunks)
    merged = {name: np.concatenate([_pad(chunk[name], width) for chunk in chunks])
              for name in chunks[0]}
    return TracedPaths(carrier_hz=carrier_hz, transmitter_enu=transmitter, receivers_enu=receivers, **merged)


def _arrays(paths: object, carrier_hz: float, scene: RayScene) -> dict[str, np.ndarray]:
    """One solver call's paths (receivers, 1 transmitter, P paths) as TracedPaths' arrays."""
    valid = np.asarray(paths.valid.numpy(), dtype=bool)[:, 0]
    delays = np.asarray(paths.tau.numpy(), dtype=np.float64)[:, 0]
    real, imag = (np.asarray(part.numpy(), dtype=np.float64)[:, 0, 0, 0] for part in paths.a)
    # Sionna's coefficient leaves the propagation phase to its channel response; ours carries it
    delays = np.where(valid, delays, 0.0)
    gains = (real + 1j * imag) * np.exp(-2j * np.pi * carrier_hz * delays)
    kinds = np.asarray(paths.interactions.numpy(), dtype=np.int64)[:, :, 0]  # (depth, N, P)
    interactions = np.bitwise_or.reduce(kinds, axis=0) if kinds.shape[0] else np.zeros_like(delays, dtype=np.int64)
    departure = np.where(valid[..., None], _unit(paths.theta_t.numpy()[:, 0], paths.phi_t.numpy()[:, 0]), 0.0)
    arrival = np.where(valid[..., None], _unit(paths.theta_r.numpy()[:, 0], paths.phi_r.numpy()[:, 0]), 0.0)
    return {"valid": valid, "delays_s": delays, "gains": np.where(valid, gains, 0.0),
            "los": valid & (interactions == 0), "interactions": interactions.astype(np.uint8),
            "departure_enu": scene.directions_to_map(departure), "arrival_enu": scene.directions_to_map(arrival)}


def _unit(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit vectors of zenith angles ``theta`` and azimuths ``phi`` (rad, scene axes)."""
    theta, phi = np.asarray(theta, dtype=np.float64), np.asarray(phi, dtype=np.float64)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def _pad(values: np.ndarray, width: int) -> np.ndarray:
    """``values`` (N, P, ...) padded with zeros (False) to P = ``width``."""
    padding = [(0, 0), (0, width - values.shape[1])] + [(0, 0)] * (values.ndim - 2)
    return np.pad(values, padding)
