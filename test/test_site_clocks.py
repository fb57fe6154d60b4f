"""Site frame clocks drift with their oscillator: the emitter's frame timing, the rendered
waveform, the ground-truth arrivals and the true sites in a bag's provenance all agree."""

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

from deepsync.bag import TRUTH_CELL_TIMING_TOPIC, BagReader, BagWriter, cell_timing_array_from_msg
from deepsync.frontend import square_law
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.render import GroupRenderer
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds
from deepsync.lte.cell import CellConfig
from deepsync.recording import record_scenario
from deepsync.sources import BagSource
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario
from deepsync.types import FRAME_SECONDS, EnvelopeChunk

REPO = Path(__file__).resolve().parents[1]
CAMPUS = REPO / "config" / "scenarios" / "campus.yaml"
NOISELESS = FrontendConfig(detector_nep_w_per_sqrt_hz=0.0, noise_temperature_k=0.0, adc_noise_lsb=0.0,
                           video_highpass_hz=0.0)
FRAME = 19200  # samples per frame at 1.92 MHz


def emitter(pci=301, timing=2.1e-3, ppb=0.0, site="A", load=0.0, re_power=2e-3, carrier=2115e6):
    return Emitter(CellConfig(pci=pci, bandwidth_mhz=10, load=load), carrier, re_power, timing,
                   ppb * 1e-9 * carrier, site, frame_rate_error=ppb * 1e-9)


# --------------------------------------------------------------------------- the emitter's clock


def test_a_site_20_ppb_fast_is_1_2_us_early_after_a_minute():
    e = emitter(timing=3120.4e-6, ppb=20.0)
    k = 6000  # 60 s of frames
    assert e.frame_start_s(k) - (e.timing_offset_s + k * FRAME_SECONDS) == pytest.approx(-1.2e-6, abs=1e-9)
    assert e.timing_drift_s_per_s == pytest.approx(-20e-9, rel=1e-12)
    # the offset is timing_offset_s at true time 0 and moves by exactly the drift
    for t in (0.0, 7.3, 60.0, 3600.0):
        assert e.timing_offset_at(t) == pytest.approx(3120.4e-6 - 20e-9 * t, abs=1e-15)
    start = e.frame_start_s(k)
    assert start - k * FRAME_SECONDS == pytest.approx(e.timing_offset_at(start), abs=1e-13)
    # frame_index_at inverts frame_start_s, right at the boundaries too
    for j in (-3, 0, 1, 6000, 360_000):
        assert e.frame_index_at(e.frame_start_s(j)) == j
        assert e.frame_index_at(np.nextafter(e.frame_start_s(j), -np.inf)) == j - 1


def test_without_drift_frame_starts_are_the_plain_grid_bit_for_bit():
    e = emitter(timing=3120.4e-6)
    for k in (-1, 0, 1, 17, 6000, 360_000):
        assert e.frame_start_s(k) == e.timing_offset_s + k * FRAME_SECONDS  # exact, not approx
        assert e.frame_slip_s(k) == 0.0
        assert e.frame_index_at(e.timing_offset_s + (k + 0.5) * FRAME_SECONDS) == k


def test_an_impossible_frame_rate_error_is_refused():
    with pytest.raises(ValueError, match="frame_rate_error"):
        emitter(ppb=float("nan"))
    with pytest.raises(ValueError, match="frame_rate_error"):
        emitter(ppb=2e6)


def test_sectors_of_one_site_must_share_their_frame_clock():
    a, b = emitter(pci=120, ppb=10.0), emitter(pci=121, ppb=10.0)
    b = replace(b, frame_rate_error=11e-9)  # same site name, carrier and offsets: one group
    sim = EnvelopeSimulator([a, b], FixedChannel(Paths([1e-6], [1e-4], [0.0])), NOISELESS, seed=1)
    with pytest.raises(ValueError, match="share one frame clock"):
        sim.analog(0, 100)


# --------------------------------------------------------------------------- the rendered waveform


class PlainGridRenderer(GroupRenderer):
    """The renderer as it was before site clocks drifted: frames on the plain 10 ms grid."""

    def frame_time(self, k):
        return self.timing_offset_s + k * FRAME_SECONDS

    def _arrival(self, k):
        first_delay = min(p.first_delay_s for p in self.paths(k))
        return k * self.frame_length + (self.timing_offset_s + first_delay) * self.rate

    def frame_at(self, sample):
        k = int(np.floor((sample / self.rate - self.timing_offset_s) / FRAME_SECONDS))
        while self.bounds(k)[0] > sample:
            k -= 1
        while self.bounds(k)[1] <= sample:
            k += 1
        return k


def test_render_without_drift_is_unchanged_bit_for_bit(monkeypatch):
    emitters = [emitter(pci=120, load=0.7, timing=3120.4e-6), emitter(pci=121, load=0.7, timing=3120.4e-6),
                emitter(pci=56, load=0.5, timing=512.3e-6, site="C", carrier=2145e6)]
    paths = [Paths([1.337e-6, 1.9e-6], [2e-4, 5e-5j], [3.0, -40.0])] * 2 + [Paths([2.71e-6], [1e-4], [0.5])]

    def analog():
        sim = EnvelopeSimulator(emitters, FixedChannel(paths), FrontendConfig(), seed=3)
        return sim.analog(0, 3 * FRAME), sim.analog(500 * FRAME, 501 * FRAME)

    now = analog()
    monkeypatch.setattr(square_law, "GroupRenderer", PlainGridRenderer)
    before = analog()
    for mine, theirs in zip(now, before):
        assert np.array_equal(mine, theirs)


def test_the_waveform_follows_the_drifting_frame_clock():
    """1000 ppb fast, 100 s in: frames come 100 us (192 samples) early, and the sync code is
    where the drifting clock puts it, to 0.01 samples."""
    delay, gain = 1.337e-6, 3e-5
    e = emitter(pci=301, timing=2.1e-3, ppb=1000.0)
    sim = EnvelopeSimulator([e], FixedChannel([Paths([delay], [gain], [0.0])]), NOISELESS, seed=2)
    templates = SyncTemplates(NOISELESS)
    for k in (10_000, 10_003):
        arrival = sim.sample_index(e.frame_start_s(k) + sync_code_offset_seconds() + delay)
        plain = sim.sample_index(e.timing_offset_s + k * FRAME_SECONDS + sync_code_offset_seconds() + delay)
        assert plain - arrival == pytest.approx((e.timing_offset_s + k * FRAME_SECONDS) * 1.92, abs=1e-3)
        assert plain - arrival > 192.0
        start = int(np.floor(arrival))
        window = sim.analog(start, start + templates.length)
        fitted = fit_delay(window, templates, 301, arrival - start)
        assert fitted == pytest.approx(arrival - start, abs=0.01)


def fit_delay(window, templates, pci, guess, span=0.6, step=0.005):
    """Sub-sample delay whose template best explains ``window`` (least squares, free offset; the
    three samples at each end carry the neighbouring symbols' filter tails)."""
    candidates = guess + np.arange(-span, span + step / 2, step)
    shapes = templates.template(pci, 0, candidates)[:, 3:-3]
    shapes = shapes - shapes.mean(axis=1, keepdims=True)
    centred = window[3:-3] - window[3:-3].mean()
    residual = np.sum((centred[None] - (shapes @ centred / np.sum(shapes**2, axis=1))[:, None] * shapes) ** 2, axis=1)
    return candidates[int(np.argmin(residual))]


# --------------------------------------------------------------------------- a recorded bag


@pytest.fixture(scope="module")
def drifting_bag(tmp_path_factory):
    """0.1 s of the campus scenario with site A 1000 ppb fast and site B 1000 ppb slow."""
    folder = tmp_path_factory.mktemp("clocks")
    text = CAMPUS.read_text()
    for old, new in (("frequency_error_ppb: 12.0", "frequency_error_ppb: 1000.0"),
                     ("frequency_error_ppb: -7.5", "frequency_error_ppb: -1000.0")):
        assert old in text
        text = text.replace(old, new, 1)
    scenario = folder / "drifting.yaml"
    scenario.write_text(text)
    out = folder / "bag"
    record_scenario(scenario, 0.1, out, workers=1, progress=False)
    return scenario, out


def test_truth_arrivals_move_between_frames_with_the_site_clock(drifting_bag):
    scenario, out = drifting_bag
    toas: dict[int, list[float]] = {}
    with BagReader(out) as bag:
        for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
            for record in cell_timing_array_from_msg(item.message).cells:
                toas.setdefault(record.pci, []).append(record.toa)
    # a static receiver on an ideal clock: each step is one frame of the site's clock
    expected = {120: FRAME / (1 + 1e-6), 121: FRAME / (1 + 1e-6), 301: FRAME / (1 - 1e-6), 56: FRAME / (1 + 3.2e-9)}
    assert sorted(toas) == sorted(expected)
    for pci, step in expected.items():
        steps = np.diff(toas[pci])
        assert len(steps) >= 8
        np.testing.assert_allclose(steps, step, rtol=0, atol=1e-6)
    assert FRAME - expected[120] == pytest.approx(0.0192, abs=1e-4)  # 10 ns a frame: measurable
    # the first arrival: the timing offset at true time 0 plus the sync offset and the path
    twin = build_twin(load_scenario(scenario))
    for i, cell in enumerate(twin.cells):
        e = twin.emitters[i]
        k = e.frame_index_at(0.0) + 1
        sent = e.frame_start_s(k)
        arrival = (sent + sync_code_offset_seconds() + twin.geometric_delay_s(i, sent)) * 1.92e6
        assert min(toas[cell.pci], key=lambda toa: abs(toa - arrival)) == pytest.approx(arrival, abs=1e-6)


def test_the_true_sites_and_origin_round_trip_through_the_bag(drifting_bag):
    scenario, out = drifting_bag
    spec = load_scenario(scenario)
    source = BagSource(out)
    sites = source.truth_sites()
    assert [s.name for s in sites] == [s.name for s in spec.sites] == ["A", "B", "C"]
    for truth, site in zip(sites, spec.sites):
        assert (truth.latitude_deg, truth.longitude_deg, truth.height_m) == (
            site.latitude_deg, site.longitude_deg, site.height_m)
        assert truth.timing_offset_us == pytest.approx(site.timing_offset_us, abs=1e-9)
        assert truth.frequency_error_ppb == site.frequency_error_ppb
        assert truth.timing_drift_ns_per_s == pytest.approx(-site.frequency_error_ppb, rel=1e-12)
    a = sites[0]
    assert a.timing_drift_ns_per_s == pytest.approx(-1000.0)
    assert a.timing_offset_us_at(60.0) == pytest.approx(3120.4 - 60.0, abs=1e-9)  # 1000 ppb: 60 us a minute
    origin = source.truth_origin()
    assert (origin.latitude_deg, origin.longitude_deg, origin.height_m) == (
        spec.origin.latitude_deg, spec.origin.longitude_deg, spec.origin.height_m)


def test_bags_without_true_sites_say_so_naming_the_bag(tmp_path):
    older = tmp_path / "older_campus"  # simulated before the sites were recorded
    provenance = json.dumps({"generator": "deepsync 0.1 simulate", "frontend": asdict(FrontendConfig())})
    with BagWriter(older, provenance=provenance):
        pass
    with pytest.raises(ValueError, match=r"older_campus: its provenance holds no true sites"):
        BagSource(older).truth_sites()
    with pytest.raises(ValueError, match=r"older_campus: its provenance holds no true origin"):
        BagSource(older).truth_origin()
    real = tmp_path / "real"
    with BagWriter(real) as bag:  # a recording from elsewhere: no provenance at all
        bag.write_envelope(EnvelopeChunk(stamp_ns=0, sample_rate=1.92e6, first_sample_index=0, adc_bits=12,
                                         volts_per_code=2 / 4096, samples=np.zeros(FRAME, np.int16)))
    with pytest.raises(ValueError, match=r"real: no simulation provenance"):
        BagSource(real).truth_sites()
