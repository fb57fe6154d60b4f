"""Training data for the timing network: simulated cells' windows, cut as the cell search cuts
them, labelled with the true first-path arrival.

One *scene* is a short simulated recording: a target cell (random PCI, bandwidth 1.4-20 MHz,
load, a TDL-A..E channel with a TR 38.901 UMa/UMi delay spread, Doppler of a receiver up to
15 m/s, received power), up to two other sites on its carrier (their intermodulation lands in
the same video band) and maybe a cell on another carrier, a receiver clock off by up to
+-0.5 ppm and site clocks drifting by up to +-50 ppb. The scene runs through the same
:class:`~deepsync.frontend.simulator.EnvelopeSimulator` as every recording (square law, video
filter, detector and RF noise, AC coupling, AGC, ADC); the stream goes through the cell search's
own :class:`~deepsync.sync.stacking.FrameStacker` (with the receiver clock known to 0.02 ppm,
as the stacker's tracking leaves it) and :func:`~deepsync.sync.windows.extract_windows`, cut
``coarse error`` whole samples away from the true code start (the sync stage's coarse
position is off by a few samples at low SNR). Every cell of a scene with a different PCI is
an example, so one simulation gives up to four.

Co-sited pairs (``cosited_share`` of the scenes): a second sector of the target's site, the
other PCI of its group, sends from the same mast with the same timing and oscillator. It sees
the target's very paths (the twin's statistical channel shares a site's fading among its
sectors) scaled by its own antenna gain and transmit-chain phase: ``cosited_power_db`` relative
to the target, a uniform phase. The two codes add before the square law, so the sync stage
reports them together with a fitted model of their sum (``deepsync.sync.sites``); the example
is that pair: one example for both sectors, its template the pair model that
:func:`~deepsync.sync.sites.fit_site` fits on the stacked frame within half a sample of the
true code start, as the search's lock leaves it. Its SNR is that fitted model's, as the sync
stage measures a pair's (below about -25 dB per frame the fit's four noise dimensions lift it).

Why whole scenes and not just the windows' symbols: the detector draws its noise per 8.5 ms
block from the block's mean power, the AC coupling carries ~3 ms of state and the AGC is set
from the first 10 ms, so a window alone is exact only as part of the stream it was cut from
(``EnvelopeSimulator.analog`` gives any window exactly, test_frontend, but at the cost of its
whole block). A scene is ``max_frames + 1`` frames long: the first settles the coupling.

``frame_means`` (F, ...): each example also holds the stacked mean frame of its scene's first
F frames (``frame_<F>``, the frame a stack of F frames hands the timing stage), turned so the
window's coarse code start is its sample 0, with that stack's ``mean_delay``
(``frame_delay_<F>``), and a pair its fit's ``site_coefficients``: what ``ml_frame``, the timing
stage's default, times a known cell with (the codes and the CRS of the whole frame), so that the
side by side can score it on the very examples the network is scored on. Not for training: one
frame is 77 kB an example against the windows' 14 kB.

``channel: clean`` replaces every TDL channel by the direct path alone (no multipath, no
fading): not for training, but the reference case in which an estimator can meet its Cramer-Rao
bound, for evaluation (``benchmarks/timing/split_variants.py clean``).

Label: ``offset`` = true code start (frame timing + sync code position + the geometric, i.e.
first-path, delay, on the receiver clock, in stream samples) minus the window's coarse index,
what the estimators return. Per-frame SNR (``sync_snr.json``'s definition): the energy of the
code's mean-removed template at the received power per RE (all paths) over the per-frame
interference energy in the code window, measured from the frame-to-frame fluctuation.

Shards: ``<split>/shard_<k>.npz`` (``SHARD_KEYS`` and the config that made it), shard k of a
split drawn from ``(seed, split, k)`` alone, so any shard is regenerated identically, missing
shards are made by a rerun (resume) and workers may make them in any order; a shard made with
another config is refused rather than mixed in; one made before a config field or shard key
existed counts as made with that field's default (``ADDED_KEYS``: what it then held).
"""

from __future__ import annotations

import enum
import json
import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepsync.configio import choice_name
from deepsync.outputs import replacing
from deepsync.schema import check_settings, resolve_choices, setting
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.simulator import EnvelopeSimulator, SimulationStats
from deepsync.frontend.templates import SyncTemplates, code_template, cosited_pair, sync_code_offset_seconds
from deepsync.jobs import JobRunner
from deepsync.lte.cell import CellConfig
from deepsync.sync.sites import fit_site
from deepsync.sync.stacking import FrameStacker, StackConfig
from deepsync.sync.windows import extract_windows
from deepsync.timing.crlb import snr_db
from deepsync.twin.propagation import delay_spread_lognormal
from deepsync.twin.tdl import TDL_PROFILES
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S

TDL_NAMES = ("TDL-A", "TDL-B", "TDL-C", "TDL-D", "TDL-E")
CLEAN_PROFILE = "clean"  # the direct path alone (``Channel.CLEAN``)
PROFILES = (*TDL_NAMES, CLEAN_PROFILE)  # index = the shards' ``profile`` code
LOS_PROFILES = frozenset({"TDL-D", "TDL-E", CLEAN_PROFILE})
BANDWIDTHS_MHZ = (1.4, 3.0, 5.0, 10.0, 15.0, 20.0)
SPLITS = {"train": 0, "val": 1, "test": 2}
CONFIG_KEY = "dataset_config"  # each shard's DatasetConfig, as JSON: data of another config is not mixed in
EIRP_PER_RE_W = 10 ** ((61 - 30) / 10) / 600  # a 61 dBm macro sector, per resource element


class Channel(enum.Enum):
    """How every cell of a scene reaches the receiver."""

    TDL = "tdl"  # a TR 38.901 TDL-A..E realisation, delay spread from UMa/UMi of its LOS state (training)
    CLEAN = "clean"  # the direct path alone, no multipath or fading: where an estimator meets its bound


@dataclass(frozen=True)
class DatasetConfig:
    """The training distribution; each shard records it, and a changed field means new data."""

    # Ranges: what a receiver can meet, and sizes far beyond the shipped run's (256 examples per
    # shard of 12 frames).
    seed: int = setting(2025, help="Seed every shard is drawn from (with its split and index).", bounds=(0, 2**63 - 1))
    max_frames: int = setting(12, help="Frames per example: the model may take any first n of them.", unit="frames",
                              bounds=(2, 100))
    window_margin: int = setting(10, help="Samples kept on either side of the code (the sync stage's default: "
                                 "windows of 276 + 2 x 10 samples).", unit="samples", bounds=(1, 100))
    max_coarse_error: int = setting(8, help="Largest distance between the coarse and the true code start.",
                                    unit="samples", bounds=(1, 99))
    re_power_dbm: tuple[float, float] = setting((-110.0, -68.0), help="Target cell's received power per resource "
                                                "element at the antenna, drawn within.", unit="dBm",
                                                bounds=(-160.0, 0.0))
    carrier_hz: float = setting(2.12e9, help="Carrier frequency (the LTE bands).", unit="Hz", bounds=(400e6, 6e9))
    max_speed_mps: float = setting(15.0, help="Largest receiver speed (Doppler).", unit="m/s", bounds=(0.0, 140.0))
    # the front end's clock_offset_ppm range
    max_clock_ppm: float = setting(0.5, help="Largest receiver clock error.", unit="ppm", bounds=(0.0, 1000.0))
    # the scenario's site oscillator range
    max_site_drift_ppb: float = setting(50.0, help="Largest site clock drift.", unit="ppb", bounds=(0.0, 1000.0))
    examples_per_shard: int = setting(256, help="Examples a shard holds.", unit="examples", bounds=(1, 65_536))
    channel: Channel = setting(Channel.TDL, help="How every cell of a scene reaches the receiver.",
                               choices={kind.value: kind for kind in Channel})
    cosited_share: float = setting(0.0, help="Share of scenes whose target has a co-sited sector (module "
                                   "docstring).", bounds=(0.0, 1.0))
    cosited_power_db: tuple[float, float] = setting((-12.0, 0.0), help="That sector's power relative to the "
                                                    "target, drawn within.", unit="dB", bounds=(-60.0, 20.0))
    frame_means: tuple[int, ...] = setting((), help="Stacked frames of each mean frame kept, increasing, at most "
                                           "max_frames (module docstring).", unit="frames", bounds=(2, 100))

    def __post_init__(self) -> None:
        if isinstance(self.frame_means, list):
            object.__setattr__(self, "frame_means", tuple(self.frame_means))
        check_settings(self)
        resolve_choices(self)  # the name, as YAML and the shards hold it
        if not 1 <= self.max_coarse_error < self.window_margin:
            raise ValueError(f"max_coarse_error: {self.max_coarse_error!r} must be 1..window_margin-1 "
                             f"({self.window_margin - 1}) so the true code stays inside the window")
        low, high = self.re_power_dbm
        if not low < high:
            raise ValueError(f"re_power_dbm: {self.re_power_dbm!r} must be an increasing pair of numbers")
        low, high = self.cosited_power_db
        if not low <= high:
            raise ValueError(f"cosited_power_db: {self.cosited_power_db!r} must be a non-decreasing pair of numbers")
        if (not all(f <= self.max_frames for f in self.frame_means)
                or list(self.frame_means) != sorted(set(self.frame_means))):
            raise ValueError(f"frame_means: {self.frame_means!r} must be increasing frame counts in 2..max_frames "
                             f"({self.max_frames})")

    def example_bytes(self, template_length: int) -> int:
        """Memory one example takes when a split is loaded: its float32 windows and template,
        its mean frames (float64, a frame each at the default front end's rate) and scalars."""
        frame = round(FrontendConfig().adc_rate_hz * FRAME_SECONDS)
        windows = self.max_frames * (template_length + 2 * self.window_margin)
        return 4 * (windows + template_length) + 8 * len(self.frame_means) * (frame + 1) + 128


@dataclass(frozen=True)
class Example:
    windows: np.ndarray  # (max_frames, W) volts, as SyncWindow.windows
    template: np.ndarray  # (T,) the PCI's code template (volts per W per RE)
    offset: float  # true first-path code start minus the coarse index (samples)
    snr_db: float  # per-frame SNR of the code
    bandwidth_mhz: float
    profile: int  # index into PROFILES
    delay_spread_ns: float
    re_power_dbm: float
    coarse_error: int
    pci: int
    other_cells: int
    cosited_pci: int  # the target's co-sited sector, timed with it as a pair; -1: a single cell
    site_coefficients: np.ndarray  # (4,) a pair's fitted model (SyncWindow.site_coefficients); NaN: a single cell
    # the config's frame_means' mean frames (each (frame samples,), coarse code start at 0) and
    # their stacks' mean_delay (samples)
    mean_frames: tuple[np.ndarray, ...] = ()
    frame_delays: tuple[float, ...] = ()


SHARD_KEYS = tuple(f.name for f in fields(Example) if f.name not in ("mean_frames", "frame_delays"))
# keys added since shards were first made, and what shards without them held: a shard resumes
# with its config's missing fields at their defaults (``_check_made_with``), so it loads so too
ADDED_KEYS = {"cosited_pci": -1, "site_coefficients": np.full(4, np.nan)}  # no pairs before cosited_share existed


def frame_key(frames: int) -> str:
    """The key of the mean frames of ``frames`` stacked frames, in a shard and in ``load_split``."""
    return f"frame_{frames}"


def frame_delay_key(frames: int) -> str:
    """The key of their stacks' ``mean_delay``."""
    return f"frame_delay_{frames}"


# -- one scene ---------------------------------------------------------------------------------


def _tdl_paths(rng: np.random.Generator, profile_name: str, delay_spread_s: float, bulk_delay_s: float,
               received_w: float, max_doppler_hz: float) -> Paths:
    """One static TDL realisation: Rayleigh taps (and the Ricean LOS tap) with their own Doppler."""
    profile = TDL_PROFILES[profile_name]
    scattered, los = profile.normalized_powers()
    delays = list(np.asarray(profile.delays) * delay_spread_s)
    gains = list(np.sqrt(scattered / 2) * (rng.standard_normal(scattered.size) + 1j * rng.standard_normal(scattered.size)))
    if los > 0:
        delays.append(0.0)
        gains.append(math.sqrt(los) * np.exp(2j * np.pi * rng.random()))
    gains = np.asarray(gains)
    gains *= math.sqrt(received_w / EIRP_PER_RE_W)
    doppler = max_doppler_hz * np.cos(2 * np.pi * rng.random(len(delays)))
    return Paths(bulk_delay_s + np.asarray(delays), gains, doppler)


def _direct_path(rng: np.random.Generator, delay_s: float, received_w: float, max_doppler_hz: float) -> Paths:
    """The line of sight alone: one path of constant power and a random phase."""
    gain = math.sqrt(received_w / EIRP_PER_RE_W) * np.exp(2j * np.pi * rng.random())
    return Paths(np.array([delay_s]), np.array([gain]), np.array([max_doppler_hz * math.cos(2 * np.pi * rng.random())]))


def _draw_profile(rng: np.random.Generator, carrier_hz: float) -> tuple[str, float]:
    """A TDL profile and a delay spread from the UMa or UMi distribution of its LOS state."""
    name = TDL_NAMES[int(rng.integers(len(TDL_NAMES)))]
    mu, sigma = delay_spread_lognormal(("UMa", "UMi")[int(rng.integers(2))], name in LOS_PROFILES, carrier_hz)
    return name, float(min(10 ** rng.normal(mu, sigma), 1.5e-6))


def simulate_scene(config: DatasetConfig, frontend: FrontendConfig, rng: np.random.Generator,
                   templates: SyncTemplates) -> list[Example]:
    """Every distinct-PCI cell of one random scene as an example (module docstring)."""
    n_same = int(rng.integers(0, 3))  # other sites on the target's carrier
    n_other_carrier = int(rng.integers(0, 2))
    pcis = rng.choice(504, size=1 + n_same + n_other_carrier, replace=False)
    emitters, paths, meta = [], [], []
    doppler_max = config.max_speed_mps * config.carrier_hz / SPEED_OF_LIGHT_M_S
    bandwidth = float(rng.choice(BANDWIDTHS_MHZ))
    for k, pci in enumerate(pcis):
        carrier = config.carrier_hz if k <= n_same else config.carrier_hz + 20e6 * (1 + int(rng.integers(2)))
        cell_bandwidth = bandwidth if k <= n_same else float(rng.choice(BANDWIDTHS_MHZ))
        load = float(rng.uniform(0.3, 1.0))
        # the others near the target's level: far weaker ones change nothing, far stronger ones
        # would bury it (the sync stage would not have found it)
        power_dbm = float(rng.uniform(*config.re_power_dbm)) if k == 0 else meta[0][3] + float(rng.uniform(-20.0, 10.0))
        profile, spread = (_draw_profile(rng, config.carrier_hz) if config.channel is Channel.TDL
                           else (CLEAN_PROFILE, 0.0))
        drift = float(rng.uniform(-1, 1)) * config.max_site_drift_ppb * 1e-9
        timing = float(rng.uniform(0, FRAME_SECONDS))
        bulk = float(rng.uniform(0.2e-6, 3.3e-6))  # 60 m .. 1 km
        emitters.append(Emitter(CellConfig(int(pci), cell_bandwidth, load), carrier, EIRP_PER_RE_W, timing,
                                float(rng.normal(0, 50.0)), f"site{k}", drift))
        received = 10 ** ((power_dbm - 30) / 10)
        doppler = doppler_max * float(rng.random())
        paths.append(_tdl_paths(rng, profile, spread, bulk, received, doppler) if config.channel is Channel.TDL
                     else _direct_path(rng, bulk, received, doppler))
        meta.append((cell_bandwidth, PROFILES.index(profile), spread, power_dbm, received))
    # drawn only when pairs are asked for: a config without them makes the data it always made
    sector = (_cosited_sector(config, rng, emitters[0], paths[0], {int(p) for p in pcis})
              if config.cosited_share > 0 and rng.random() < config.cosited_share else None)
    if sector is not None:
        emitters.append(sector[0])
        paths.append(sector[1])
    clock_ppm = float(rng.uniform(-1, 1)) * config.max_clock_ppm
    frontend = replace(frontend, clock_offset_ppm=clock_ppm, clock_drift_ppm_per_s=0.0)
    simulator = EnvelopeSimulator(emitters, FixedChannel(paths), frontend, seed=int(rng.integers(2**31)))
    rate = frontend.adc_rate_hz
    stats = SimulationStats()
    chunks = list(simulator.stream((config.max_frames + 1) * FRAME_SECONDS, stats=stats))
    gain = 10 ** (stats.gain_db / 20)  # ADC volts per diode volt
    frame = round(rate * FRAME_SECONDS)
    stacking = StackConfig(n_frames=config.max_frames, clock_ppm=clock_ppm + float(rng.uniform(-0.02, 0.02)),
                           track_clock=False, max_drift_samples=10.0)
    samples = np.concatenate([c.samples for c in chunks]).astype(np.float64) * frontend.volts_per_code
    stacks = FrameStacker(rate, stacking).push_samples(samples[frame:], frame, rate)
    if not stacks:
        return []
    stack = stacks[0]
    # as a stack of F frames would hold it: the same stream through a stacker of F frames
    shorter = [FrameStacker(rate, replace(stacking, n_frames=f)).push_samples(samples[frame:], frame, rate)[0]
               for f in config.frame_means]
    first_s = float(simulator.clock.true_time(stack.first_sample_index / rate))
    examples = []
    for k, emitter in enumerate(emitters[: len(pcis)]):  # a co-sited sector is its target's pair
        bandwidth_k, profile, spread, power_dbm, received = meta[k]
        # the first subframe-0 code (first path) to arrive in the stack's first frame
        travel = sync_code_offset_seconds() + paths[k].first_delay_s
        sent = emitter.frame_start_s(emitter.frame_index_at(first_s - travel) + 1)
        arrival = float(simulator.sample_index(sent + travel))
        coarse_error = int(rng.integers(-config.max_coarse_error, config.max_coarse_error + 1))
        cut = math.floor(arrival) - stack.first_sample_index + coarse_error
        if cut < config.window_margin or cut + templates.length + config.window_margin > stack.frame_samples:
            continue  # across the frame edge: the rows would be cut circularly (rare; keeps labels simple)
        windows = extract_windows(stack, cut, templates.length, config.window_margin)
        cosited = -1 if k > 0 or sector is None else sector[0].cell.pci
        coefficients = np.full(4, np.nan)
        if cosited < 0:
            template, scale = code_template(templates, emitter.cell.pci), received * gain
        else:  # fitted where the search's refined lock would put it: within half a sample
            lock = arrival - stack.first_sample_index + float(rng.uniform(-0.5, 0.5))
            fit, _ = fit_site(templates, stack.mean - stack.mean.mean(), cosited_pair(emitter.cell.pci, cosited),
                              round(lock) % stack.frame_samples, lock - round(lock))
            template, scale = fit.template(templates), 1.0  # the fit is in volts already
            coefficients = np.array(fit.coefficients)
        examples.append(Example(
            windows=windows, template=template.astype(np.float32),
            offset=arrival - (stack.first_sample_index + cut),
            snr_db=_snr_db(windows, template, scale, config.window_margin),
            bandwidth_mhz=bandwidth_k, profile=profile, delay_spread_ns=spread * 1e9,
            re_power_dbm=power_dbm, coarse_error=coarse_error, pci=emitter.cell.pci,
            other_cells=len(pcis) - 1, cosited_pci=cosited, site_coefficients=coefficients,
            mean_frames=tuple(np.roll(s.mean, -cut).astype(np.float32) for s in shorter),
            frame_delays=tuple(s.mean_delay for s in shorter)))
    return examples


def _cosited_sector(config: DatasetConfig, rng: np.random.Generator, target: Emitter, target_paths: Paths,
                    taken: set[int]) -> tuple[Emitter, Paths] | None:
    """Another sector of the target's site (module docstring): the other PCI of its group not in
    ``taken``, the same mast, timing and oscillator, the target's paths scaled by its own gain
    and phase. None when both of the group's other PCIs are taken."""
    group = target.cell.pci - target.cell.pci % 3
    free = [pci for pci in range(group, group + 3) if pci not in taken]
    if not free:
        return None
    pci = free[int(rng.integers(len(free)))]
    relative = 10 ** (float(rng.uniform(*config.cosited_power_db)) / 20) * np.exp(2j * np.pi * rng.random())
    sector = replace(target, cell=CellConfig(pci, target.cell.bandwidth_mhz, float(rng.uniform(0.3, 1.0))))
    return sector, Paths(target_paths.delays_s, target_paths.gains * relative, target_paths.doppler_hz)


def _snr_db(windows: np.ndarray, template: np.ndarray, scale: float, margin: int) -> float:
    """Per-frame SNR of the code at ``scale`` volts per (W per RE), against the frame-to-frame
    interference in the code window (the definition of ``crlb.snr_db``)."""
    inner = windows[:, margin : margin + len(template)].astype(np.float64)
    residual = inner - inner.mean(axis=0)
    residual -= residual.mean(axis=1, keepdims=True)
    noise_variance = float(np.sum(residual**2)) / ((len(inner) - 1) * len(template))
    return max(snr_db(scale, template, noise_variance), -99.0)


# -- shards ------------------------------------------------------------------------------------


def shard_path(root: Path, split: str, index: int) -> Path:
    return Path(root) / split / f"shard_{index:05d}.npz"


def make_shard(config: DatasetConfig, split: str, index: int, frontend: FrontendConfig | None = None) -> dict[str, np.ndarray]:
    """Shard ``index`` of ``split``: ``examples_per_shard`` examples from ``(seed, split, index)``."""
    frontend = frontend or FrontendConfig()
    templates = SyncTemplates(frontend)
    rng = np.random.default_rng([config.seed, SPLITS[split], index])
    examples: list[Example] = []
    while len(examples) < config.examples_per_shard:
        examples += simulate_scene(config, frontend, rng, templates)
    examples = examples[: config.examples_per_shard]
    arrays = {key: np.asarray([getattr(e, key) for e in examples]) for key in SHARD_KEYS}
    arrays["windows"] = arrays["windows"].astype(np.float32)
    arrays["template"] = arrays["template"].astype(np.float32)
    for k, frames in enumerate(config.frame_means):
        arrays[frame_key(frames)] = np.asarray([e.mean_frames[k] for e in examples])
        arrays[frame_delay_key(frames)] = np.asarray([e.frame_delays[k] for e in examples])
    arrays[CONFIG_KEY] = np.array(_config_json(config))
    return arrays


def _config_json(config: DatasetConfig) -> str:
    return json.dumps(asdict(config), sort_keys=True, default=choice_name)


def _write_shard(config: DatasetConfig, root: Path, split: str, index: int) -> int:
    path = shard_path(root, split, index)
    arrays = make_shard(config, split, index)
    path.parent.mkdir(parents=True, exist_ok=True)
    # atomic: an interrupted write leaves no shard, so a rerun makes it again
    with replacing(path) as temporary, temporary.open("wb") as handle:
        np.savez(handle, **arrays)
    return len(arrays["offset"])


def _check_made_with(path: Path, config: DatasetConfig) -> None:
    """ValueError unless the shard at ``path`` was made with ``config`` (resuming must not mix data)."""
    with np.load(path, allow_pickle=False) as shard:
        made = json.loads(str(shard[CONFIG_KEY])) if CONFIG_KEY in shard.files else None
    if made is not None:  # a field added since the shard was made: it had the default's effect then
        made = {**json.loads(_config_json(DatasetConfig())), **made}
    wanted = json.loads(_config_json(config))
    if made != wanted:
        changed = "no record of it" if made is None else ", ".join(
            f"{key} {made.get(key)!r} -> {value!r}" for key, value in wanted.items() if made.get(key) != value)
        raise ValueError(f"{path} was made with another dataset config ({changed}): remove the shards of "
                         f"{path.parent.parent} or choose another data directory")


def generate(root: Path, shards: dict[str, int], config: DatasetConfig | None = None, workers: int = 1,
             ray: str | None = None) -> int:
    """Make every missing shard of ``shards`` (split -> count) under ``root``; returns how many
    examples were made. Existing shards are kept: an interrupted run resumes. Shards are made
    in ``workers`` local processes, or as tasks on the Ray cluster ``ray`` names
    (``deepsync.jobs``): the same shards either way, each written atomically by its job."""
    config = config or DatasetConfig()
    jobs = []
    for split, count in shards.items():
        for k in range(count):
            path = shard_path(root, split, k)
            if path.exists():
                _check_made_with(path, config)
            else:
                jobs.append((config, Path(root), split, k))
    made = 0
    with tqdm(total=len(jobs) * config.examples_per_shard, desc="timing examples", unit="ex") as bar:
        for count in JobRunner(workers, ray).map(_write_shard, jobs):
            made += count
            bar.update(config.examples_per_shard)
    return made


def load_split(root: Path, split: str, shards: int | None = None) -> dict[str, np.ndarray]:
    """Every shard of a split (the first ``shards`` of them: what a run config counted on, and
    bounded the memory of), concatenated (``SHARD_KEYS``, and the mean frames every shard
    holds: ``frame_key``); ValueError when there is none."""
    paths = sorted((Path(root) / split).glob("shard_*.npz"))[:shards]
    if not paths:
        raise ValueError(f"no shards in {Path(root) / split}: `deepsync train` makes them")
    parts = []
    for path in paths:
        with np.load(path, allow_pickle=False) as shard:
            missing = [key for key in SHARD_KEYS if key not in shard.files and key not in ADDED_KEYS]
            if missing:
                raise ValueError(f"{path}: not a timing shard (missing {', '.join(missing)})")
            count = len(shard["offset"])
            part = {key: shard[key] for key in shard.files if key != CONFIG_KEY}
            for key in SHARD_KEYS:
                if key not in part:
                    default = ADDED_KEYS[key]
                    part[key] = np.broadcast_to(default, (count, *np.shape(default)))
            parts.append(part)
    keys = [key for key in parts[0] if all(key in part for part in parts)]
    return {key: np.concatenate([part[key] for part in parts]) for key in keys}
