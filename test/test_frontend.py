"""The envelope-detector chain against independent, brute-force computations of the physics."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.fft
import scipy.signal

from deepsync.frontend.adc import ReceiverClock, cubic_sample
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.square_law import output_noise_density
from deepsync.frontend.plan import plan_clusters
from deepsync.frontend.render import emitter_seed
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds
from deepsync.frontend.video import VideoFilter
from deepsync.lte.cell import CellConfig
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import Numerology
from deepsync.lte.ofdm import modulate
from deepsync.types import FRAME_SECONDS

# noise off, and DC-coupled so the diode-output volts of ``analog`` and the templates are
# the same quantity (AC coupling is applied later, in the ADC stage)
NOISELESS = FrontendConfig(
    detector_nep_w_per_sqrt_hz=0.0, noise_temperature_k=0.0, adc_noise_lsb=0.0, video_highpass_hz=0.0
)
ADC_RATE = NOISELESS.adc_rate_hz


def single_path(delay_s: float, gain: complex = 1e-4) -> Paths:
    return Paths([delay_s], [gain], [0.0])


def emitter(pci=121, carrier=2115e6, bandwidth=10, load=0.6, site="A", timing=0.0, re_power=1e-3):
    return Emitter(CellConfig(pci=pci, bandwidth_mhz=bandwidth, load=load), carrier, re_power, timing, 0.0, site)


def reference_detector_output(emitters, paths, seed, fft_size, frames, center_hz, indices=None):
    """Brute force: whole frames modulated at one rate, delayed by whole samples, shifted to
    their carrier offset, summed, squared, and filtered in one long FFT with the video H(f).
    ``indices`` are the emitters' positions in the simulated list (they pick the content)."""
    rate = fft_size * 15e3
    length = frames * round(rate * FRAME_SECONDS)
    total = np.zeros(length, dtype=np.complex128)
    for i, e, p in zip(indices or range(len(emitters)), emitters, paths):
        num = Numerology.for_bandwidth(e.cell.bandwidth_mhz, fft_size=fft_size)
        generator = FrameGenerator(e.cell, emitter_seed(seed, i))
        x = np.concatenate([modulate(generator.grid(k), num) for k in range(frames)])
        delay = (e.timing_offset_s + p.delays_s[0]) * rate
        assert abs(delay - round(delay)) < 1e-9, "reference supports whole-sample delays only"
        shifted = np.zeros(length, dtype=np.complex128)
        shifted[round(delay) :] = x[: length - round(delay)]
        n = np.arange(length)
        total += p.gains[0] * np.sqrt(e.re_power_w) * shifted * np.exp(2j * np.pi * (e.carrier_hz - center_hz) * n / rate)
    power = np.abs(total) ** 2
    frequencies = scipy.fft.rfftfreq(length, 1 / rate)
    video = VideoFilter(NOISELESS)
    filtered = scipy.fft.irfft(scipy.fft.rfft(power) * video.response(frequencies), n=length)
    gain = NOISELESS.detector_responsivity_v_per_w * NOISELESS.rf_power_gain
    return gain * filtered[:: int(round(rate / ADC_RATE))]


def test_single_carrier_noiseless_equals_lowpassed_square():
    emitters = [emitter()]
    paths = [single_path(37 / 15.36e6, 2e-4 * np.exp(0.3j))]
    sim = EnvelopeSimulator(emitters, FixedChannel(paths), NOISELESS, seed=4)
    cluster = sim.detector.clusters[0].cluster
    assert cluster.fft_size == 1024  # 10 MHz + the video stop band fits the standard rate
    reference = reference_detector_output(emitters, paths, 4, cluster.fft_size, 6, cluster.center_hz)
    n0, n1 = 2 * 19200, 4 * 19200  # away from the reference's circular wrap
    simulated = sim.analog(n0, n1)
    np.testing.assert_allclose(simulated, reference[n0:n1], rtol=0, atol=1e-6 * np.abs(reference).max())
    # the simulated video filter is the analog Butterworth to within its -57 dB stop-band taper
    video, f = VideoFilter(NOISELESS), np.linspace(0, 10e6, 2001)
    assert np.max(np.abs(video.response(f) - video.analog_response(f))) < 1.5e-3


def test_adjacent_carriers_and_shared_carrier_intermodulate_exactly():
    # Two sectors of one site on 2115 MHz and a different site on the adjacent 2125 MHz
    # carrier: one cluster; its cross terms must match a brute-force square of the sum.
    emitters = [
        emitter(pci=120, site="A"),
        emitter(pci=121, site="A"),
        emitter(pci=56, carrier=2125e6, site="C", timing=2e-3),
    ]
    sim = EnvelopeSimulator(emitters, FixedChannel([single_path(0), single_path(0), single_path(0)]), NOISELESS, 9)
    (cluster,) = [c.cluster for c in sim.detector.clusters]
    rate_guess = cluster.sample_rate_hz
    paths = [single_path(11 / rate_guess, 2e-4), single_path(11 / rate_guess, 1.5e-4j), single_path(5 / rate_guess, 1e-4)]
    sim = EnvelopeSimulator(emitters, FixedChannel(paths), NOISELESS, 9)
    assert len(sim.detector.clusters) == 1
    reference = reference_detector_output(emitters, paths, 9, cluster.fft_size, 5, cluster.center_hz)
    n0, n1 = 2 * 19200, 3 * 19200
    np.testing.assert_allclose(sim.analog(n0, n1), reference[n0:n1], atol=1e-6 * np.abs(reference).max())

    # the intermodulation is physically significant in the ADC band
    separate = sum(
        reference_detector_output([e], [p], 9, cluster.fft_size, 5, cluster.center_hz, [i])[n0:n1]
        for i, (e, p) in enumerate(zip(emitters, paths))
    )
    cross = reference[n0:n1] - separate
    assert np.std(cross) > 0.1 * np.std(separate - separate.mean())


def test_far_carriers_are_separate_clusters_and_their_cross_term_is_out_of_band():
    far = [emitter(pci=1), emitter(pci=2, carrier=2145e6, site="B")]
    clusters = plan_clusters(far, VideoFilter(NOISELESS).stopband_hz)
    assert [c.emitter_indices for c in clusters] == [(0,), (1,)]
    # Brute force at 69.12 MHz, holding both carriers, each transmitted band-limited to its
    # channel (as ACLR requires of a real eNodeB): the square's cross term lands near 30 MHz,
    # and what reaches the ADC of it is negligible next to each carrier's own envelope.
    rate, frames = 69.12e6, 2
    num = Numerology.for_bandwidth(10)
    n = np.arange(round(rate * FRAME_SECONDS * frames))
    carriers = []
    for i, e in enumerate(far):
        generator = FrameGenerator(e.cell, emitter_seed(1, i))
        native = np.concatenate([modulate(generator.grid(k), num) for k in range(frames)])
        upsampled = scipy.signal.resample(native, len(n))  # ideal band-limited interpolation
        carriers.append(1e-4 * upsampled * np.exp(2j * np.pi * (e.carrier_hz - 2130e6) * n / rate))
    video = VideoFilter(NOISELESS)
    frequencies = scipy.fft.rfftfreq(len(n), 1 / rate)

    def detect(x):
        return scipy.fft.irfft(scipy.fft.rfft(np.abs(x) ** 2) * video.response(frequencies), n=len(n))

    both, each = detect(carriers[0] + carriers[1]), detect(carriers[0]) + detect(carriers[1])
    middle = slice(len(n) // 4, 3 * len(n) // 4)
    assert np.std(both[middle] - each[middle]) < 1e-4 * np.std(each[middle])


@pytest.mark.parametrize("signal_scale", [1e-5, 1e-2])  # noise x noise, then signal x noise dominant
def test_rf_noise_through_square_law_matches_analytic_density(signal_scale):
    rng = np.random.default_rng(0)
    num = Numerology.for_bandwidth(5)
    cell = CellConfig(pci=7, bandwidth_mhz=5, load=1.0)
    signal = np.concatenate([modulate(FrameGenerator(cell, 1).grid(k), num) for k in range(4)]) * signal_scale
    rate = num.sample_rate_hz
    # 80 dB noise figure makes the thermal noise big enough to measure against the signal
    config = FrontendConfig(noise_figure_db=80.0, rf_gain_db=0.0, rf_bandwidth_hz=rate, detector_nep_w_per_sqrt_hz=0.0)
    n0 = 1.380649e-23 * 290.0 * 1e8
    noise = (rng.standard_normal(len(signal)) + 1j * rng.standard_normal(len(signal))) * np.sqrt(n0 * rate / 2)
    excess = np.abs(signal + noise) ** 2 - np.abs(signal) ** 2
    frequencies, psd = scipy.signal.welch(excess, fs=rate, nperseg=8192, return_onesided=False)
    in_band = np.abs(frequencies) < 0.3e6  # where N0^2 (B - |f|) is still ~ N0^2 B
    expected = output_noise_density(config, np.mean(np.abs(signal) ** 2))
    assert np.mean(psd[in_band]) == pytest.approx(expected, rel=0.05)


def fit_delay(window, templates: SyncTemplates, pci, guess, span=0.6, step=0.005):
    """Sub-sample delay whose template best explains ``window`` (least squares, free offset).

    The first and last three samples are left out: the video filter smears the neighbouring
    symbols (CRS before, PBCH after) into them, which no template describes."""
    candidates = guess + np.arange(-span, span + step / 2, step)
    inner = slice(3, -3)
    shapes = templates.template(pci, 0, candidates)[:, inner]
    shapes = shapes - shapes.mean(axis=1, keepdims=True)
    centred = window[inner] - window[inner].mean()
    scale = shapes @ centred / np.sum(shapes**2, axis=1)
    residual = np.sum((centred[None] - scale[:, None] * shapes) ** 2, axis=1)
    best = int(np.argmin(residual))
    return candidates[best], scale[best], 1 - residual[best] / np.sum(centred**2)


@pytest.mark.parametrize("clock_ppm, drift", [(0.0, 0.0), (40.0, 0.5)])
def test_sync_code_lands_where_ground_truth_says(clock_ppm, drift):
    """Averaged over frames, the envelope at the true arrival is the template at that delay."""
    config = replace(NOISELESS, clock_offset_ppm=clock_ppm, clock_drift_ppm_per_s=drift)
    delay = 1.337e-6
    timing = 2.1e-3
    gain = 3e-5
    e = emitter(pci=301, load=0.0, timing=timing, re_power=2e-3)
    sim = EnvelopeSimulator([e], FixedChannel([single_path(delay, gain)]), config, seed=2)
    templates = SyncTemplates(config)
    frames = range(1, 30)
    arrivals = [sim.sample_index(timing + k * FRAME_SECONDS + sync_code_offset_seconds() + delay) for k in frames]
    analog = sim.analog(0, int(max(arrivals)) + 400)
    for arrival in arrivals[::7]:
        start = int(np.floor(arrival))
        window = analog[start : start + templates.length]
        fitted, scale, explained = fit_delay(window, templates, 301, arrival - start)
        assert fitted == pytest.approx(arrival - start, abs=0.01)
        assert scale == pytest.approx(e.re_power_w * gain**2, rel=0.05)
        assert explained > 0.999  # load 0: nothing but the code inside the window


def test_loaded_cell_sync_code_is_where_ground_truth_says_on_average():
    config = NOISELESS
    delay = 4.2e-6
    e = emitter(pci=88, load=1.0, re_power=2e-3)
    sim = EnvelopeSimulator([e], FixedChannel([single_path(delay, 3e-5)]), config, seed=6)
    templates = SyncTemplates(config)
    arrival0 = sim.sample_index(sync_code_offset_seconds() + delay)
    analog = sim.analog(0, 60 * 19200)
    start = int(np.floor(arrival0))
    windows = np.array([analog[start + 19200 * k : start + 19200 * k + templates.length] for k in range(60)])
    fitted, _, explained = fit_delay(windows.mean(axis=0), templates, 88, arrival0 - start)
    # 60 frames of a fully loaded 10 MHz cell (-15 dB each) leave ~0.05 samples of noise
    assert fitted == pytest.approx(arrival0 - start, abs=0.15)
    assert explained > 0.5


def test_receiver_clock_round_trip_and_sampling():
    clock = ReceiverClock(offset_ppm=25.0, drift_ppm_per_s=-0.3)
    t = np.linspace(0, 600, 7)
    np.testing.assert_allclose(clock.true_time(clock.receiver_time(t)), t, rtol=0, atol=1e-12)
    assert clock.receiver_time(100.0) == pytest.approx(100.0 * (1 + 25e-6) - 0.5 * 0.3e-6 * 100.0**2)
    # a sine at 0.05 cycles per sample is interpolated within the cubic error (-72 dB there)
    x = np.sin(2 * np.pi * 0.05 * np.arange(400))
    positions = np.linspace(10.0, 380.0, 999)
    assert np.max(np.abs(cubic_sample(x, 0, positions) - np.sin(2 * np.pi * 0.05 * positions))) < 5e-4
    with pytest.raises(ValueError):
        cubic_sample(x, 0, np.array([0.5]))


def test_templates_shift_exactly_and_differ_between_cells():
    templates = SyncTemplates(NOISELESS)
    assert templates.length == 276
    one = templates.template(121, 0, np.array([0.0, 1.0, 0.25]))
    np.testing.assert_allclose(one[1, 1:], one[0, :-1], atol=1e-9 * np.abs(one).max())
    assert not np.allclose(one[2], one[0])
    everything = templates.all()
    assert everything.shape == (504, 2, 276)
    flat = everything.reshape(1008, -1)
    assert len({row.tobytes() for row in flat}) == 1008
    # the video filter delays the envelope: nothing before the code, its tail inside the window
    assert np.all(np.abs(everything[:, :, 0]) < 1e-3 * np.abs(everything).max())
    np.testing.assert_allclose(everything[121, 0], one[0])


def test_worker_processes_give_the_single_process_stream_bit_for_bit():
    """Work units are spread over processes (a pipe each) and read back in order: the stream
    must not depend on how many there are."""
    from pathlib import Path

    from deepsync.twin import build_twin
    from deepsync.twin.scenario import load_scenario

    twin = build_twin(load_scenario(Path(__file__).resolve().parents[1] / "config" / "scenarios" / "campus.yaml"))

    def stream(workers: int) -> np.ndarray:
        simulator = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, 7)
        return np.concatenate([chunk.samples for chunk in simulator.stream(2.2, workers=workers)])

    assert np.array_equal(stream(1), stream(3))  # three units on three processes, the last one short


def test_the_analog_output_of_any_window_is_the_streams():
    """``analog`` is a pure function of the sample range, noise included: a cell's code window
    computed on its own (what a windowed training-example generator needs) equals the same
    samples of the whole stream, bit for bit, wherever the window falls."""
    from pathlib import Path

    from deepsync.twin import build_twin
    from deepsync.twin.scenario import load_scenario

    twin = build_twin(load_scenario(Path(__file__).resolve().parents[1] / "config" / "scenarios" / "campus.yaml"))
    whole = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, 7).analog(0, 2 * 19200)
    for start in (0, 5000, 16200, 19100, 30000):  # in a video block, across one (at 16336), across a frame
        alone = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, 7).analog(start, start + 296)
        np.testing.assert_array_equal(alone, whole[start : start + 296])


class _VanishingPathChannel:
    """Emitter 0: a weak early path that vanishes at ``switch_s`` (the earliest arrival then jumps
    a microsecond later, as a ray-traced channel's may from one traced point to the next);
    emitter 1, another site, steady."""

    def __init__(self, switch_s: float) -> None:
        self.switch_s = switch_s

    def paths(self, emitter_index: int, t: float) -> Paths:
        if emitter_index == 1:
            return single_path(3e-6, 1e-4)
        if t < self.switch_s:
            return Paths([1e-6, 2e-6], [1e-7, 2e-4], [0.0, 0.0])
        return single_path(2e-6, 2e-4)


def test_an_earliest_path_that_vanishes_leaves_no_gap_in_the_stream():
    emitters = [emitter(pci=120, site="A"), emitter(pci=56, carrier=2125e6, site="C", timing=2e-3)]
    jumping = EnvelopeSimulator(emitters, _VanishingPathChannel(0.025), NOISELESS, seed=3)
    steady = EnvelopeSimulator(emitters, _VanishingPathChannel(-1.0), NOISELESS, seed=3)
    frame = round(ADC_RATE * FRAME_SECONDS)
    out = jumping.analog(0, 6 * frame)
    assert out.shape == (6 * frame,) and np.all(np.isfinite(out))
    # from two frames after the jump the stream is the steady channel's (the weak path's share of
    # the power was -66 dB): nothing was lost or repeated at the jump
    later = slice(4 * frame, 6 * frame)
    np.testing.assert_allclose(out[later], steady.analog(0, 6 * frame)[later], atol=1e-5 * np.abs(out).max())
