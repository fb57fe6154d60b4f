"""rosbag2 bags: the envelope topic as recorded (by ``deepsync simulate`` or on a robot).

A bag carries ADC codes already, so nothing is converted: chunks are the envelope messages,
gaps and all (the sync stage reports them). The front end is the one the bag says it was
recorded with (the provenance ``deepsync simulate`` writes, into ``metadata.yaml`` and into the
``.mcap`` file itself, so an ``.mcap`` copied alone keeps it); a bag recorded elsewhere gets the
default envelope-detector chain at the rate of its own first envelope message.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepsync.bag import (
    ENVELOPE_TOPIC,
    PROVENANCE_KEY,
    TRUTH_CELL_TIMING_TOPIC,
    BagError,
    BagReader,
    cell_timing_array_from_msg,
    provenance_document,
    read_envelope,
)
from deepsync.configio import ConfigError, load_yaml
from deepsync.frontend.config import FrontendConfig
from deepsync.geo import LocalFrame
from deepsync.towers import MapOrigin, TowerDatabase
from deepsync.types import EnvelopeChunk
from .base import check_rate


def is_bag_path(path: str | os.PathLike) -> bool:
    """A rosbag2 directory (with ``metadata.yaml``, or at least an ``.mcap`` file) or an
    ``.mcap`` file, by its name and kind."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file() or any(x.suffix.lower() == ".mcap" for x in p.iterdir())
    return p.suffix.lower() == ".mcap"


def bag_dir(path: str | os.PathLike) -> Path:
    """Where to open the bag ``path`` names: a bag directory as is; an ``.mcap`` file's
    directory when that directory's ``metadata.yaml`` lists the file (so that it is checked
    against the file), else the file alone (which carries its provenance itself)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag (path does not exist)")
    if p.is_dir() or p.suffix.lower() != ".mcap":
        return p
    metadata = p.parent / "metadata.yaml"
    if metadata.is_file():
        try:
            files = load_yaml(metadata)["rosbag2_bagfile_information"]["relative_file_paths"]
        except (ConfigError, KeyError, TypeError):
            return p
        if isinstance(files, list) and p.name in files:
            return p.parent
    return p


def bag_frontend(path: str | os.PathLike) -> FrontendConfig:
    """The front end a bag was recorded with (from its provenance); for a bag without one, the
    default front end at the sample rate of its first envelope message.

    Templates must match the chain that made the stream; a bag from ``deepsync simulate`` says
    which one that was. Raises :class:`~deepsync.bag.BagError` (a ValueError) naming the bag
    for unreadable provenance, or for a bag without provenance and without envelope messages.
    """
    where = bag_dir(path)
    with BagReader(where) as bag:
        provenance = bag.custom_data.get(PROVENANCE_KEY)
    return _frontend(where, provenance)


def _frontend(where: Path, provenance: str | None) -> FrontendConfig:
    if provenance:
        return recorded_frontend(provenance, None, where)
    first = next(iter(read_envelope(where)), None)
    if first is None:
        raise BagError(f"{where}: no provenance and no {ENVELOPE_TOPIC} messages: the sample rate is unknown")
    return recorded_frontend(None, first.sample_rate, where)


def recorded_frontend(provenance: str | None, sample_rate: float | None, where: str | os.PathLike) -> FrontendConfig:
    """The front end a bag's provenance names, else the default chain at ``sample_rate`` (the
    stream's, from its first message); BagError naming the bag when neither works."""
    if provenance:
        document = provenance_document(provenance, where)
        try:
            return FrontendConfig(**document["frontend"])
        except (ValueError, KeyError, TypeError) as error:
            raise BagError(f"{where}: unreadable front-end provenance ({error})") from None
    try:
        return FrontendConfig(adc_rate_hz=sample_rate)
    except (TypeError, ValueError) as error:
        raise BagError(f"{where}: no default front end at {sample_rate!r} Hz: {error}") from None


@dataclass(frozen=True)
class TruthSite:
    """A simulated site as it really was (what a perfect tower database would hold).

    ``height_m`` is the antenna height above ground; ``timing_offset_us`` the frame timing
    offset at the bag's first sample, which then changes by ``timing_drift_ns_per_s`` per
    second of true time (the site's frame clock runs ``frequency_error_ppb`` fast, so the drift
    is -``frequency_error_ppb``).
    """

    name: str
    latitude_deg: float
    longitude_deg: float
    height_m: float
    timing_offset_us: float
    timing_drift_ns_per_s: float
    frequency_error_ppb: float

    def timing_offset_us_at(self, seconds: float) -> float:
        """The frame timing offset (us) ``seconds`` of true time after the first sample."""
        return self.timing_offset_us + self.timing_drift_ns_per_s * 1e-3 * seconds


def _truth_fields(cls: type, value: object, where: str) -> object:
    """``cls`` from one provenance mapping: every field present, names a string, numbers finite."""
    if not isinstance(value, dict):
        raise BagError(f"{where} is not a mapping")
    fields = cls.__dataclass_fields__
    missing = [name for name in fields if name not in value]
    if missing:
        raise BagError(f"{where} lacks {', '.join(missing)}")
    parsed = {}
    for name in fields:
        item = value[name]
        if name == "name":
            if not isinstance(item, str):
                raise BagError(f"{where}.name {item!r} is not a string")
        elif isinstance(item, bool) or not isinstance(item, int | float) or not math.isfinite(item):
            raise BagError(f"{where}.{name} {item!r} is not a finite number")
        else:
            item = float(item)
        parsed[name] = item
    return cls(**parsed)


class BagSource:
    """The envelope topic of a rosbag2 bag: ``path`` is the bag directory or its ``.mcap``."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = bag_dir(path)
        with BagReader(self.path) as bag:
            provenance = bag.custom_data.get(PROVENANCE_KEY)
            self.n_chunks = bag.message_counts.get(ENVELOPE_TOPIC, 0)
            self._has_truth = TRUTH_CELL_TIMING_TOPIC in bag.topics
            self.inconsistencies = bag.inconsistencies
            """Where the bag's ``metadata.yaml`` disagrees with its ``.mcap`` (which is used)."""
        self._provenance = bool(provenance)
        self._provenance_text = provenance
        self.frontend = _frontend(self.path, provenance)
        check_rate(self.frontend.adc_rate_hz, f"{self.path} (recorded at)")
        self.center_hz: float | None = None  # an envelope detector sees every carrier in its RF band

    @property
    def description(self) -> str:
        chain = "recorded front end" if self._provenance else "default front end (no provenance)"
        text = (f"rosbag2 bag {self.path}: {self.n_chunks} envelope chunks at "
                f"{self.frontend.adc_rate_hz / 1e6:g} MS/s, {chain}")
        if self.inconsistencies:
            text += f"; metadata.yaml and the .mcap disagree in {len(self.inconsistencies)} point(s)"
        return text

    def chunks(self) -> Iterator[EnvelopeChunk]:
        """The envelope messages in log-time order, as recorded."""
        return read_envelope(self.path)

    def truth_arrivals(self) -> dict[int, np.ndarray]:
        """PCI -> every true sync-code arrival of the cell (``toa``, stream samples, sorted) in the
        bag's ground truth; empty for a bag without ground truth. The arrivals move with the
        receiver and the site clocks, so compare an estimate with the nearest one in time."""
        arrivals: dict[int, list[float]] = {}
        if not self._has_truth:
            return {}
        with BagReader(self.path) as bag:
            for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
                for record in cell_timing_array_from_msg(item.message).cells:
                    arrivals.setdefault(record.pci, []).append(record.toa)
        return {pci: np.sort(np.array(toas)) for pci, toas in arrivals.items()}

    def _truth(self, key: str) -> object:
        """One key of the provenance ``deepsync simulate`` wrote; ValueError (BagError) naming
        the bag where there is none: a real recording, or a bag from before that key."""
        if not self._provenance_text:
            raise BagError(f"{self.path}: no simulation provenance, so no true {key} (a real recording?)")
        info = provenance_document(self._provenance_text, self.path)
        if key not in info:
            raise BagError(f"{self.path}: its provenance holds no true {key} (recorded by an older "
                           "deepsync simulate, or not simulated)")
        return info[key]

    def truth_sites(self) -> list[TruthSite]:
        """The simulated sites as they really were (positions, timing offsets at the first
        sample and their drift, oscillator errors), in scenario order. Raises a ValueError
        (:class:`~deepsync.bag.BagError`) naming the bag if it holds no such truth."""
        sites = self._truth("sites")
        if not isinstance(sites, list):
            raise BagError(f"{self.path}: provenance sites is not a list")
        return [_truth_fields(TruthSite, site, f"{self.path}: provenance sites[{i}]")
                for i, site in enumerate(sites)]

    def scenario_path(self) -> Path:
        """The scenario file the bag was simulated from, as its provenance names it (it may since
        have moved). Raises a ValueError (:class:`~deepsync.bag.BagError`) naming the bag if it
        names none."""
        scenario = self._truth("scenario")
        if not isinstance(scenario, str) or not scenario:
            raise BagError(f"{self.path}: provenance scenario {scenario!r} is not a path")
        return Path(scenario)

    def truth_origin(self) -> MapOrigin:
        """The simulated scenario's map-frame origin. Raises a ValueError
        (:class:`~deepsync.bag.BagError`) naming the bag if it holds no such truth."""
        return _truth_fields(MapOrigin, self._truth("origin"), f"{self.path}: provenance origin")

    def check_frame(self, towers: TowerDatabase) -> None:
        """:func:`check_same_frame` of this bag and ``towers``."""
        check_same_frame(self._provenance_text, self.path, towers)


def check_same_frame(provenance: str | None, where: str | os.PathLike, towers: TowerDatabase | None) -> None:
    """ValueError when a bag says where its ``map`` frame lies (a simulation's origin, in its
    ``provenance``) and ``towers`` puts its origin elsewhere: the ground truth (in the bag's
    frame) and the fixes (in the database's) would be compared, or written side by side, as if
    they shared one, every position off by the distance between the origins. A bag that does
    not say (a real recording) or a database without an origin has nothing to compare."""
    if towers is None or towers.origin is None:
        return
    info = provenance_document(provenance, where)
    if "origin" not in info:
        return
    recorded = _truth_fields(MapOrigin, info["origin"], f"{where}: provenance origin")
    origin = towers.origin
    frame = LocalFrame(origin.latitude_deg, origin.longitude_deg, origin.height_m)
    apart = float(np.linalg.norm(frame.geodetic_to_enu(recorded.latitude_deg, recorded.longitude_deg,
                                                       recorded.height_m)))
    if apart > FRAME_TOLERANCE_M:
        raise ValueError(
            f"{where}: its map frame has its origin at {_where(recorded)} (the simulation's), tower database "
            f"{towers.name!r} at {_where(origin)}, {apart:,.2f} m apart: the ground truth and the fixes would "
            "be compared in two frames; give the database the bag's origin")


FRAME_TOLERANCE_M = 0.01
"""How far two map frames' origins may lie apart and still be one frame: far below any error
the evaluation reports (metres), far above the rounding of a coordinate written with 9 decimals."""


def _where(origin: MapOrigin) -> str:
    return f"({origin.latitude_deg:.7f}, {origin.longitude_deg:.7f}, {origin.height_m:g} m)"
