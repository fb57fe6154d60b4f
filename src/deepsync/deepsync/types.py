"""What the stages hand each other, their health reports, and the physical constants they share.

The pipeline runs in one direction (DESIGN.md): a *source* yields :class:`EnvelopeChunk` s, the
sync stage turns them into one :class:`SyncWindow` per detected cell, the timing stage into one
:class:`CellTiming` per cell, and fusion into a :class:`Fix` or a :class:`NoFix`. Each type
mirrors a message of ``deepsync_msgs`` (or a standard one), so a ROS node converts it field by
field and a stage fed from a message sees exactly what it would have seen in process.

Nothing here imports the rest of the project: every module may import this one.

What goes wrong is reported, never raised, as :class:`Health`: a closed set of kinds
(:class:`HealthKind`), each with the :class:`Severity` a ``diagnostic_msgs/DiagnosticStatus``
level maps to, plus a message for people.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

SPEED_OF_LIGHT_M_S = 299_792_458.0
FRAME_SECONDS = 10e-3  # an LTE radio frame; every cell repeats its sync codes once per frame
HALF_FRAME_SECONDS = FRAME_SECONDS / 2  # the PSS repeats every half-frame (subframes 0 and 5)
MAX_PCI = 503  # physical cell identities are 0..503 (TS 36.211 6.11)
# LTE's largest cells (PRACH format 3) reach ~100 km: no receiver hears a site farther away.
MAX_CELL_RANGE_M = 100e3
# The variance of what a fix does not measure (a 2-D fix's height, any orientation): huge, so a
# consumer's filter (robot_localization) takes it as no information, finite so it stays a number.
UNMEASURED_VARIANCE = 1e6


class Severity(enum.IntEnum):
    """How bad a health report is; the values are ``diagnostic_msgs/DiagnosticStatus`` levels."""

    OK = 0
    WARN = 1
    ERROR = 2


class HealthKind(enum.Enum):
    """Everything a stage reports about its input or its output, as a closed set.

    Stream events (something happened at a sample index; data around it was dropped):
    ``GAP``, ``NOT_FINITE``, ``CORRUPT``, ``BACKWARDS``, ``RESTART``, ``RATE_MISMATCH``. Live
    sources (a receiver's byte stream): ``SOURCE_STALLED`` (no bytes for a while),
    ``SOURCE_CLOSED`` (the stream ended or its connection failed); samples a live source had to
    drop are a ``GAP``. Stack flags (a stack was searched,
    but its result deserves less trust, or none): ``CLIPPED``, ``NO_SIGNAL``, ``MISALIGNED``.
    Timing: ``UNTIMEABLE`` (a cell's windows could not be timed at all), ``WEAK_TIMING`` (an
    arrival whose 1-sigma says it may be far off), ``SMEARED_PEAK`` (a cell's correlation peak
    wider than a single path's, its 1-sigma widened: multipath may hold it late). Fusion:
    ``UNANCHORED`` (a heard cell the tower database cannot place: unknown PCI, reused PCI
    without a carrier, site without position or timing), ``AIDING_REFUSED`` (a GNSS fix or an odometry velocity fusion did not use: not a
    number, back in time, stale, or refused by the tracker's innovation test).
    """

    GAP = "gap"  # samples missing from the stream: the stack spanning them is dropped
    NOT_FINITE = "not_finite"  # NaN or inf samples: the stack spanning them is dropped
    CORRUPT = "corrupt"  # codes no ADC of the stated bits makes: the stack spanning them is dropped
    BACKWARDS = "backwards"  # a late or repeated chunk, from before what was already received: dropped
    RESTART = "restart"  # the stream started over (index back, a driver restart): stacking starts afresh
    RATE_MISMATCH = "rate_mismatch"  # a chunk at another rate than the templates': dropped
    SOURCE_STALLED = "source_stalled"  # a live stream sent no bytes for its stall time
    SOURCE_CLOSED = "source_closed"  # a live stream closed, or could not be (re)connected
    CLIPPED = "clipped"  # too many samples at the ADC rails (or the recording's)
    NO_SIGNAL = "no_signal"  # silent or stuck input: nothing is searched
    MISALIGNED = "misaligned"  # receiver clock drift smeared the stack's frames
    UNTIMEABLE = "untimeable"  # a detected cell's windows carry nothing to time
    WEAK_TIMING = "weak_timing"  # an arrival beyond the estimator's threshold: its 1-sigma is large
    SMEARED_PEAK = "smeared_peak"  # a cell's correlation peak wider than one path's: its 1-sigma widened
    UNANCHORED = "unanchored"  # a heard cell fusion cannot use: the database does not place it
    AIDING_REFUSED = "aiding_refused"  # a GNSS fix or odometry velocity fusion could not or would not use

    @property
    def severity(self) -> Severity:
        return _SEVERITY[self]


_SEVERITY = {
    HealthKind.GAP: Severity.WARN,
    HealthKind.NOT_FINITE: Severity.WARN,
    HealthKind.CORRUPT: Severity.ERROR,
    HealthKind.BACKWARDS: Severity.WARN,
    HealthKind.RESTART: Severity.WARN,
    HealthKind.RATE_MISMATCH: Severity.ERROR,
    HealthKind.SOURCE_STALLED: Severity.WARN,
    HealthKind.SOURCE_CLOSED: Severity.ERROR,
    HealthKind.CLIPPED: Severity.WARN,
    HealthKind.NO_SIGNAL: Severity.ERROR,
    HealthKind.MISALIGNED: Severity.WARN,
    HealthKind.UNTIMEABLE: Severity.WARN,
    HealthKind.WEAK_TIMING: Severity.WARN,
    HealthKind.SMEARED_PEAK: Severity.WARN,
    HealthKind.UNANCHORED: Severity.WARN,
    HealthKind.AIDING_REFUSED: Severity.WARN,
}


@dataclass(frozen=True)
class Health:
    """One report: its kind, what happened in words, and where in the stream (if at a point)."""

    kind: HealthKind
    message: str
    sample_index: int | None = None

    @property
    def severity(self) -> Severity:
        return self.kind.severity

    def __str__(self) -> str:
        return f"{self.kind.value}: {self.message}"


MAX_CHUNK_SAMPLES = 2**22
"""Samples an envelope chunk may hold (8 MiB of codes; 2.2 s at 1.92 MS/s, 68 ms at 61.44 MS/s):
sources and nodes send one 10 ms frame per chunk, and the stages' working copies of a chunk
take tens of bytes per sample, so a bag message of 200 million samples took 5 GB."""


@dataclass(frozen=True)
class EnvelopeChunk:
    """A contiguous run of raw ADC codes (``deepsync_msgs/EnvelopeSamples``).

    ``first_sample_index`` counts samples since the stream began and is monotonic across
    chunks, so a gap shows up as a jump; ``stamp_ns`` is the receiver-clock time of the first
    sample (ns). ``samples`` are the raw int16 codes; volts = code * ``volts_per_code``.
    """

    stamp_ns: int
    sample_rate: float
    first_sample_index: int
    adc_bits: int
    volts_per_code: float
    samples: np.ndarray

    def __post_init__(self) -> None:
        if np.size(self.samples) > MAX_CHUNK_SAMPLES:
            raise ValueError(f"EnvelopeChunk of {np.size(self.samples):,} samples: at most {MAX_CHUNK_SAMPLES:,} "
                             "(a stream comes in chunks of about a frame)")
        samples = _as_codes(self.samples)
        if not (np.isfinite(self.sample_rate) and self.sample_rate > 0):
            raise ValueError(f"EnvelopeChunk.sample_rate {self.sample_rate!r} must be > 0")
        if self.first_sample_index < 0:
            raise ValueError("EnvelopeChunk.first_sample_index must be >= 0")
        if not 1 <= self.adc_bits <= 16:
            raise ValueError(f"EnvelopeChunk.adc_bits {self.adc_bits!r} must be 1..16")
        if not (np.isfinite(self.volts_per_code) and self.volts_per_code > 0):
            raise ValueError(f"EnvelopeChunk.volts_per_code {self.volts_per_code!r} must be > 0")
        object.__setattr__(self, "samples", samples)

    @property
    def end_sample_index(self) -> int:
        """Index one past the last sample: the next chunk's ``first_sample_index`` if no gap."""
        return self.first_sample_index + len(self.samples)


def _as_codes(samples: object) -> np.ndarray:
    """ADC codes as contiguous little-endian int16, or ValueError: a cast would turn NaN into 0
    and wrap 40000 to -25536 without a word, so only whole numbers within int16 pass."""
    values = np.asarray(samples)
    if values.ndim != 1:
        raise ValueError(f"EnvelopeChunk.samples must be 1-D, got shape {values.shape}")
    if values.dtype.kind not in "biuf":
        raise ValueError(f"EnvelopeChunk.samples must be numbers (ADC codes), got dtype {values.dtype}")
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"EnvelopeChunk.samples[{i}] is {values[i]}: ADC codes are whole numbers")
        fractional = values != np.round(values)
        if fractional.any():
            i = int(np.argmax(fractional))
            raise ValueError(f"EnvelopeChunk.samples[{i}] is {values[i]}: ADC codes are whole numbers")
    if values.size and values.dtype != np.int16 and (values.min() < -(2**15) or values.max() > 2**15 - 1):
        i = int(np.argmax((values < -(2**15)) | (values > 2**15 - 1)))
        raise ValueError(f"EnvelopeChunk.samples[{i}] is {values[i]}: beyond int16, where ADC codes travel")
    return np.ascontiguousarray(values, dtype="<i2")


@dataclass(frozen=True)
class SyncWindow:
    """One detected cell, ready for a timing estimator (``deepsync_msgs/SyncWindow``).

    ``windows`` has one row per stacked frame: the envelope (volts) from a margin before the
    coarse code start to the same margin after the code's template ends, so the margin is
    ``(window_length - template length) / 2``. ``coarse_index`` is the stream sample index of
    the subframe-0 code start in the stack's first frame, to a whole sample; the timing stage
    refines it. A co-sited sector found together with this one (``cosited_pci``) shares the
    windows, and ``site_coefficients`` then give the pair's fitted code model (scales of
    |s_a|^2, |s_b|^2, 2Re(s_a s_b*), 2Im(s_a s_b*), a the lower PCI of the two).
    ``bandwidth_mhz`` (from a tower database) lets the timing stage time the cell by its whole
    known frame (codes and CRS) in the stack's mean frame (``StackWindows.frame``).
    """

    stamp_ns: int  # receiver time of the stack's first sample
    pci: int
    coarse_index: int
    windows: np.ndarray  # (n_frames, window_length) float32, volts
    peak_metric: float  # detection statistic, in sigmas of its noise
    snr_db: float  # code energy over residual energy in the stacked code windows
    earfcn: int | None = None
    carrier_hz: float | None = None
    cosited_pci: int | None = None
    site_coefficients: tuple[float, float, float, float] | None = None
    bandwidth_mhz: float | None = None  # the cell's channel bandwidth, if the tower database gives it

    def __post_init__(self) -> None:
        if not 0 <= self.pci <= MAX_PCI:
            raise ValueError(f"SyncWindow.pci {self.pci!r} must be 0..{MAX_PCI}")
        if self.bandwidth_mhz is not None and not (math.isfinite(self.bandwidth_mhz) and self.bandwidth_mhz > 0):
            raise ValueError(f"SyncWindow.bandwidth_mhz {self.bandwidth_mhz!r} must be > 0 MHz or None")
        windows = np.ascontiguousarray(self.windows, dtype=np.float32)
        if windows.ndim != 2 or 0 in windows.shape:
            raise ValueError(f"SyncWindow.windows must be (n_frames, window_length), got shape {windows.shape}")
        if (self.cosited_pci is None) != (self.site_coefficients is None):
            raise ValueError("SyncWindow: cosited_pci and site_coefficients come together or not at all")
        if self.cosited_pci is not None and not (0 <= self.cosited_pci <= MAX_PCI and self.cosited_pci != self.pci):
            raise ValueError(f"SyncWindow.cosited_pci {self.cosited_pci!r} must be another PCI in 0..{MAX_PCI}")
        if self.site_coefficients is not None and len(self.site_coefficients) != 4:
            raise ValueError("SyncWindow.site_coefficients must hold 4 values")
        object.__setattr__(self, "windows", windows)

    @property
    def n_frames(self) -> int:
        return self.windows.shape[0]

    @property
    def window_length(self) -> int:
        return self.windows.shape[1]


@dataclass(frozen=True)
class CellTiming:
    """One cell's time of arrival in stream samples (``deepsync_msgs/CellTiming``): an estimate,
    or the ground truth of a simulated recording.

    ``toa`` is the fractional stream sample index of the subframe-0 sync-code start, ``toa_std``
    its honest 1-sigma in samples (0 for ground truth), ``crlb_std`` the Cramer-Rao bound of
    that estimate at its measured amplitude and noise (NaN where not computed), ``estimator``
    names who produced it, ``flags`` what deserves attention about it. ``earfcn`` (if known)
    tells apart two sites that reuse a PCI on different carriers; ``amplitude`` is the fitted
    sync-code envelope amplitude (volts, proportional to received power through the square law).
    """

    pci: int
    toa: float
    toa_std: float
    snr_db: float
    estimator: str
    crlb_std: float = math.nan
    flags: tuple[Health, ...] = field(default=())
    earfcn: int | None = None
    amplitude: float = math.nan

    def __post_init__(self) -> None:
        if not 0 <= int(self.pci) <= MAX_PCI:
            raise ValueError(f"CellTiming.pci {self.pci!r} must be 0..{MAX_PCI}")
        if not math.isfinite(self.toa):
            raise ValueError(f"CellTiming.toa {self.toa!r} must be finite")
        if not (math.isfinite(self.toa_std) and self.toa_std >= 0):
            raise ValueError(f"CellTiming.toa_std {self.toa_std!r} must be finite and >= 0")


def _check_time_base(stack: StackArrivals | StackWindows) -> None:
    """A stack's sample rate and measured clock drift: ValueError naming the type and field."""
    name = type(stack).__name__
    if not (math.isfinite(stack.sample_rate) and stack.sample_rate > 0):
        raise ValueError(f"{name}.sample_rate {stack.sample_rate!r} must be > 0")
    if stack.clock_drift_ppm is not None and not math.isfinite(stack.clock_drift_ppm):
        raise ValueError(f"{name}.clock_drift_ppm {stack.clock_drift_ppm!r} must be finite or None")
    if stack.stack is not None:
        frames, hop = stack.stack
        if not (isinstance(frames, int) and isinstance(hop, int) and 1 <= hop <= frames):
            raise ValueError(f"{name}.stack {stack.stack!r} must be (n_frames, hop_frames) with 1 <= hop_frames "
                             "<= n_frames, or None")


@dataclass(frozen=True)
class StackArrivals:
    """The arrivals of one stack and the time base they are read on (``CellTimingArray``).

    Stream sample ``first_sample_index`` was taken at receiver time ``stamp_ns``, so a cell's
    arrival is at receiver time ``stamp_ns + (toa - first_sample_index) / sample_rate``.
    ``clock_drift_ppm`` is the receiver clock error the sync stage measured (None: unknown).
    ``stack`` is (n_frames, hop_frames) of the stacks the arrivals were timed in (None: not
    said, as in a ground truth): sliding stacks share frames, and fusion counts that.
    """

    stamp_ns: int
    first_sample_index: int
    sample_rate: float
    cells: tuple[CellTiming, ...]
    clock_drift_ppm: float | None = None
    stack: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        _check_time_base(self)
        object.__setattr__(self, "cells", tuple(self.cells))

    def seconds_after_stamp(self, cell: CellTiming) -> float:
        """Receiver time of ``cell``'s arrival after ``stamp_ns`` (s)."""
        return (cell.toa - self.first_sample_index) / self.sample_rate


@dataclass(frozen=True)
class StackWindows:
    """The cells the sync stage cut from one stack, on the stack's time base (``SyncWindowArray``).

    The same time base as :class:`StackArrivals`, which the timing stage makes of it: stream
    sample ``first_sample_index`` was taken at receiver time ``stamp_ns``; ``clock_drift_ppm``
    is the receiver clock error the sync stage measured (None: unknown). ``frame`` (None: not
    sent) is the stack's mean frame (volts), its sample 0 at ``first_sample_index``: where the
    timing stage finds a known cell's CRS, which is spread over the whole frame. What repeats
    sits ``frame_delay`` samples later in it than in the stack's first frame, whose time base
    the windows and every arrival use: the rows' mean receiver-clock remainder
    (``Stack.mean_delay``), 0.086 samples per ppm of clock offset for a 10-frame stack.
    ``stack`` is (n_frames, hop_frames) of the stacks the sync stage cut (None: not said).
    """

    stamp_ns: int
    first_sample_index: int
    sample_rate: float
    windows: tuple[SyncWindow, ...]
    clock_drift_ppm: float | None = None
    frame: np.ndarray | None = None  # (frame_samples,) float32, volts
    frame_delay: float = 0.0  # samples
    stack: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        _check_time_base(self)
        if not math.isfinite(self.frame_delay):
            raise ValueError(f"StackWindows.frame_delay {self.frame_delay!r} must be finite")
        object.__setattr__(self, "windows", tuple(self.windows))
        if self.frame is not None:
            frame = np.asarray(self.frame, dtype=np.float32)
            if frame.ndim != 1 or frame.size == 0:
                raise ValueError(f"StackWindows.frame must be one frame of samples, got shape {frame.shape}")
            object.__setattr__(self, "frame", frame)

    def arrivals(self, cells: Sequence[CellTiming]) -> StackArrivals:
        """The timing stage's arrivals of these cells, on this stack's time base."""
        return StackArrivals(self.stamp_ns, self.first_sample_index, self.sample_rate, tuple(cells),
                             self.clock_drift_ppm, self.stack)


class NoFixReason(enum.Enum):
    """Why fusion produced no position (a closed set, like :class:`HealthKind`)."""

    TOO_FEW_SITES = "too_few_sites"  # fewer usable sites heard than unknowns
    UNKNOWN_SITES = "unknown_sites"  # every heard cell lacks a database position or timing
    DEGENERATE_GEOMETRY = "degenerate_geometry"  # sites (nearly) collinear: the position is not determined
    NOT_CONVERGED = "not_converged"  # the solver did not converge
    INCONSISTENT = "inconsistent"  # the arrivals contradict each other beyond their sigmas
    NOT_INITIALISED = "not_initialised"  # the tracker has not yet heard enough sites to start
    TRACK_LOST = "track_lost"  # the tracker's own uncertainty grew beyond what is worth publishing


class FixKind(enum.Enum):
    """Who made a fix."""

    SNAPSHOT = "snapshot"  # one stack's arrivals, solved on their own
    TRACKED = "tracked"  # the tracker's state after its latest update (or prediction)


@dataclass(frozen=True)
class Fix:
    """A position in the ``map`` frame (ENU metres at the configured origin, REP-105) with its
    covariance, from the arrivals of the named sites (``rejected``: heard, but outliers)."""

    stamp_ns: int
    position_enu: tuple[float, float, float]
    covariance: np.ndarray  # (3, 3) m^2, ENU; an unmeasured up axis carries UNMEASURED_VARIANCE
    sites: tuple[str, ...]
    kind: FixKind = FixKind.SNAPSHOT
    rejected: tuple[str, ...] = ()
    gdop: float = math.nan
    clock_bias_m: float = math.nan  # receiver clock bias against the sites' frame timing, times c

    @property
    def horizontal_std_m(self) -> float:
        """Root of the trace of the horizontal covariance (DRMS, m)."""
        return float(math.sqrt(max(self.covariance[0, 0] + self.covariance[1, 1], 0.0)))


@dataclass(frozen=True)
class NoFix:
    """No position for the data stamped ``stamp_ns``, and why."""

    stamp_ns: int
    reason: NoFixReason
    message: str
    rejected: tuple[str, ...] = ()


@dataclass(frozen=True)
class PositionPrior:
    """Where the receiver is believed to be, told from outside the chain (an operator's initial
    pose, the last known position of a tracker that was switched off): ``map`` ENU metres and
    their covariance (m^2; an up axis nobody knows carries :data:`UNMEASURED_VARIANCE`).

    Where the heard sites alone cannot fix a position (two sites give a hyperbola, not a
    point), a tracker started from a prior can: it keeps the prior's uncertainty along what the
    sites do not measure, and grows it as the receiver moves. Raises ValueError naming the
    field that is not a finite position or a symmetric positive-definite covariance. It holds
    from when it is given: the tracker starts from it at the next stack.

    ``heading_rad`` (with its 1-sigma ``heading_std_rad``), where known: the way the receiver's
    body faces in ``map`` (rad from east, counter-clockwise; RViz's drag), which with the
    odometry's own heading at that moment gives the odometry frame's yaw at once.
    """

    position_enu: tuple[float, float, float]
    covariance: np.ndarray  # (3, 3) m^2, ENU
    heading_rad: float | None = None
    heading_std_rad: float | None = None

    def __post_init__(self) -> None:
        position = tuple(float(v) for v in self.position_enu)
        if len(position) != 3 or not all(math.isfinite(v) for v in position):
            raise ValueError(f"position_enu: {self.position_enu!r} is not 3 finite ENU metres")
        object.__setattr__(self, "position_enu", position)
        object.__setattr__(self, "covariance", _covariance(self.covariance, 3, "covariance (m^2)"))
        if (self.heading_rad is None) != (self.heading_std_rad is None):
            raise ValueError(f"heading_rad {self.heading_rad!r} and heading_std_rad {self.heading_std_rad!r}: give "
                             "both or neither")
        if self.heading_rad is not None:
            if not _real(self.heading_rad):
                raise ValueError(f"heading_rad: {self.heading_rad!r} is not a finite angle (rad)")
            if not (_real(self.heading_std_rad) and 0 < self.heading_std_rad <= math.pi):
                raise ValueError(f"heading_std_rad: {self.heading_std_rad!r} must be in (0, pi] rad")
            object.__setattr__(self, "heading_rad", wrap_angle(float(self.heading_rad)))
            object.__setattr__(self, "heading_std_rad", float(self.heading_std_rad))

    @property
    def tightest_std_m(self) -> float:
        """The 1-sigma (m) along the prior's best-known direction."""
        return float(math.sqrt(np.linalg.eigvalsh(self.covariance)[0]))

    def widened(self, min_std_m: float) -> PositionPrior:
        """This prior with no direction known better than ``min_std_m`` (m): the covariance's
        eigenvalues raised to at least ``min_std_m^2`` along its own axes, wider ones kept. An
        operator's click claims what the tool's default says (RViz: 0.5 m), not what the click
        knows; a tracker held by an overconfident prior runs inconsistent and may refuse the
        sites that contradict it. ValueError for a floor that is not a finite number >= 0."""
        if not (math.isfinite(min_std_m) and min_std_m >= 0):
            raise ValueError(f"min_std_m: {min_std_m!r} must be a finite number of metres >= 0")
        variances, axes = np.linalg.eigh(self.covariance)
        if variances[0] >= min_std_m**2:
            return self
        widened = (axes * np.maximum(variances, min_std_m**2)) @ axes.T
        return PositionPrior(self.position_enu, 0.5 * (widened + widened.T), self.heading_rad, self.heading_std_rad)


@dataclass(frozen=True)
class GnssFix:
    """A position from outside the chain, stamped on the receiver clock: a GNSS fix (a
    ``sensor_msgs/NavSatFix``), a surveyed point passed on the way. WGS84 latitude, longitude
    and ellipsoidal height; ``covariance_enu`` in m^2 (east, north, up), or None when the
    receiver gives none (fusion then takes its configured sigma). ``frame_id`` names the
    antenna that made it. Raises ValueError naming the field that is not a number it can use."""

    stamp_ns: int
    latitude_deg: float
    longitude_deg: float
    height_m: float
    covariance_enu: np.ndarray | None = field(default=None, compare=False)
    frame_id: str = ""

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns, "GnssFix")
        if not (_real(self.latitude_deg) and abs(self.latitude_deg) <= 90):
            raise ValueError(f"GnssFix.latitude_deg {self.latitude_deg!r} is not a latitude (-90..90)")
        if not (_real(self.longitude_deg) and abs(self.longitude_deg) <= 180):
            raise ValueError(f"GnssFix.longitude_deg {self.longitude_deg!r} is not a longitude (-180..180)")
        if not _real(self.height_m):
            raise ValueError(f"GnssFix.height_m {self.height_m!r} is not a finite number")
        if self.covariance_enu is not None:
            object.__setattr__(self, "covariance_enu", _covariance(self.covariance_enu, 3, "GnssFix.covariance_enu"))


@dataclass(frozen=True)
class OdometryVelocity:
    """A horizontal velocity from outside the chain (a robot's wheel or visual odometry),
    stamped on the receiver clock: ``velocity`` (m/s) along the axes of the frame it is
    expressed in, with its covariance (m^2/s^2). ``in_map_frame``: those axes are the ``map``
    frame's (east, north); else they are an odometry frame's, turned by an unknown yaw that the
    tracker estimates. ``heading_rad``, where known: the way the body faces in that frame (the
    odometry pose's yaw). Raises ValueError naming the field that is not a number it can use."""

    stamp_ns: int
    velocity: tuple[float, float]
    covariance: np.ndarray = field(compare=False)
    in_map_frame: bool = False
    heading_rad: float | None = None

    def __post_init__(self) -> None:
        _check_stamp(self.stamp_ns, "OdometryVelocity")
        velocity = tuple(self.velocity)
        if len(velocity) != 2 or not all(_real(v) for v in velocity):
            raise ValueError(f"OdometryVelocity.velocity {self.velocity!r} is not two finite m/s")
        if self.heading_rad is not None and not _real(self.heading_rad):
            raise ValueError(f"OdometryVelocity.heading_rad {self.heading_rad!r} is not a finite angle (rad)")
        object.__setattr__(self, "velocity", tuple(float(v) for v in velocity))
        object.__setattr__(self, "covariance", _covariance(self.covariance, 2, "OdometryVelocity.covariance"))


def wrap_angle(angle: float) -> float:
    """``angle`` (rad) in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and math.isfinite(value)


def _check_stamp(stamp_ns: object, what: str) -> None:
    if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool) or stamp_ns < 0:
        raise ValueError(f"{what}.stamp_ns {stamp_ns!r} is not a time (integer nanoseconds >= 0)")


def _covariance(value: object, size: int, where: str) -> np.ndarray:
    """A read-only symmetric positive-definite ``size`` x ``size`` matrix, or ValueError naming ``where``."""
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where} is not a matrix of numbers") from None
    if matrix.shape != (size, size) or not np.all(np.isfinite(matrix)):
        raise ValueError(f"{where} must be a finite {size}x{size} matrix, got shape {matrix.shape}")
    if not np.allclose(matrix, matrix.T, rtol=1e-9, atol=1e-12 + 1e-9 * float(np.abs(matrix).max())):
        raise ValueError(f"{where} is not symmetric")
    if not np.all(np.linalg.eigvalsh(matrix) > 0):
        raise ValueError(f"{where} is not positive definite (every axis needs a variance > 0)")
    matrix.setflags(write=False)
    return matrix
