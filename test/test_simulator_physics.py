"""The simulator keeps its physics and its bits: against the simulator before its rewrite for
speed, and across the SIMD and BLAS kernels a CPU can choose.

``data/simulator_reference.npz`` holds diode-output windows (``EnvelopeSimulator.analog``, 5 ms
each) recorded by the simulator at commit 15941dd, before the rewrite that cut its work, with
the cases below (``record`` run against that commit). The rewrite computes the same discrete
model (the same content, channels, |x|^2 at the cluster rate, video filter, sampling), so the
noiseless outputs must agree to float32 rounding; the noise is drawn differently (in the
frequency domain at the ADC's samples, one deviate per sample), so its realisation differs
while its power must not.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.lte.cell import CellConfig
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
REFERENCE = Path(__file__).parent / "data" / "simulator_reference.npz"
FRAME = 19200
WINDOW = FRAME // 2
NOISELESS = dict(detector_nep_w_per_sqrt_hz=0.0, noise_temperature_k=0.0)
# float32 rounding in a different order of operations: observed 5-7e-7 RMS, 4e-6 at most
RMS_TOLERANCE = 1e-5
PEAK_TOLERANCE = 2e-5


def scenario(name: str, **frontend) -> EnvelopeSimulator:
    twin = build_twin(load_scenario(REPO / "config" / "scenarios" / f"{name}.yaml"))
    return EnvelopeSimulator(twin.emitters, twin.channel, replace(twin.frontend, **frontend), twin.scenario.seed)


def mixed(**frontend) -> EnvelopeSimulator:
    """One cluster of a 10, a 5 and a 1.4 MHz carrier off the 15 kHz grid (site oscillators,
    whole-bin and residual offsets), a 20 MHz carrier in a cluster of its own, two sectors of
    one site, multipath with Doppler from static to per-symbol, a drifting site clock and a
    receiver clock off by 0.37 ppm and drifting (the ADC samples between the video samples)."""
    cells = [
        (CellConfig(120, 10, 0.7), 2115.0e6, 3120.4e-6, 25.0, "A", 12e-9),
        (CellConfig(121, 10, 0.4), 2115.0e6, 3120.4e-6, 25.0, "A", 12e-9),
        (CellConfig(301, 5, 1.0, cfi=3), 2123.3e6, 7420.85e-6, -16.0, "B", -7.5e-9),
        (CellConfig(56, 1.4, 0.5, cfi=4), 2109.1e6, 512.3e-6, 3.0, "C", 800e-9),
        (CellConfig(7, 20, 0.9), 2150.0e6, 9000.0e-6, -40.0, "D", 0.0),
    ]
    emitters = [Emitter(c, f, 2e-3, t, off, site, ppb) for c, f, t, off, site, ppb in cells]
    rng = np.random.default_rng(11)
    paths = []
    for i, doppler in enumerate((150.0, 150.0, 4.0, 0.0, 40.0)):
        delays = 1.1e-6 + i * 0.37e-6 + np.array([0.0, 0.12e-6, 0.4e-6, 1.3e-6])
        gains = 3e-5 * (rng.standard_normal(4) + 1j * rng.standard_normal(4)) * np.array([1, 0.5, 0.3, 0.1])
        paths.append(Paths(delays, gains, doppler * np.cos(rng.uniform(0, 2 * np.pi, 4))))
    config = replace(FrontendConfig(clock_offset_ppm=0.37, clock_drift_ppm_per_s=0.02), **frontend)
    return EnvelopeSimulator(emitters, FixedChannel(paths), config, seed=5)


# name -> (simulator, [first ADC sample of each window]); stored noiseless, and as they are
# for the cases in NOISY
CASES = {
    "campus": (lambda **f: scenario("campus", **f), [0, 150 * FRAME + 1234]),  # 2 clusters, 3 sites, static
    "mixed": (mixed, [0, 370 * FRAME + 77]),
    "drive": (lambda **f: scenario("route_drive", **f), [200 * FRAME + 5]),  # 15 m/s: gains per symbol
}
NOISY = ("campus", "drive")


def record() -> dict[str, np.ndarray]:
    """The reference windows, as stored."""
    return {f"{name}{suffix}_{k}": make(**noise).analog(n0, n0 + WINDOW).astype(np.float32)
            for name, (make, starts) in CASES.items()
            for suffix, noise in (("", {}), ("_noiseless", NOISELESS)) if noise or name in NOISY
            for k, n0 in enumerate(starts)}


@pytest.fixture(scope="module")
def reference():
    with np.load(REFERENCE) as data:
        return dict(data)


@pytest.mark.parametrize("name, k", [(n, k) for n, (_, starts) in CASES.items() for k in range(len(starts))])
def test_the_noiseless_output_is_the_reference_simulators(reference, name, k):
    make, starts = CASES[name]
    want = reference[f"{name}_noiseless_{k}"].astype(np.float64)
    got = make(**NOISELESS).analog(starts[k], starts[k] + WINDOW)
    scale = np.std(want)
    assert np.sqrt(np.mean((got - want) ** 2)) < RMS_TOLERANCE * scale
    assert np.max(np.abs(got - want)) < PEAK_TOLERANCE * scale


@pytest.mark.parametrize("name, k", [(n, k) for n in NOISY for k in range(len(CASES[n][1]))])
def test_the_noise_has_the_reference_power(reference, name, k):
    """Detector and RF noise: another draw of the same process. Its power in the window (the
    noisy output less the noiseless one) matches the reference's within 10 %, which the
    ~4000 independent samples of a 0.9 MHz noise in 5 ms allow."""
    make, starts = CASES[name]
    n0 = starts[k]
    want = np.var(reference[f"{name}_{k}"].astype(np.float64) - reference[f"{name}_noiseless_{k}"])
    got = np.var(make().analog(n0, n0 + WINDOW) - make(**NOISELESS).analog(n0, n0 + WINDOW))
    assert got == pytest.approx(want, rel=0.1)


# --------------------------------------------------------------------------- any CPU

DIGEST = """
import hashlib, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from test_simulator_physics import CASES
digest = hashlib.sha256()
for name, (make, starts) in CASES.items():
    digest.update(make().analog(starts[-1], starts[-1] + 2 * 19200).tobytes())
simulator = CASES["campus"][0]()
digest.update(np.concatenate([c.samples for c in simulator.stream(0.03)]).tobytes())
print(digest.hexdigest())
"""


def simd_variants() -> dict[str, dict[str, str]]:
    """Environments that make numpy and OpenBLAS pick other kernels on this machine: numpy
    without any of its run-time SIMD extensions (back to the SSE3/ASIMD baseline), without only
    AVX-512 (an AVX2 machine's kernels, where the CPU has AVX-512), and OpenBLAS on an older
    core's kernels."""
    from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    found = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    variants = {"numpy baseline kernels": {"NPY_DISABLE_CPU_FEATURES": ",".join(found)}} if found else {}
    avx512 = [f for f in found if f.startswith("AVX512")]
    if avx512:
        variants["numpy without AVX-512"] = {"NPY_DISABLE_CPU_FEATURES": ",".join(avx512)}
    core = {"x86_64": "Nehalem", "aarch64": "ARMV8"}.get(platform.machine())
    if core:
        variants[f"OpenBLAS {core} kernels"] = {"OPENBLAS_CORETYPE": core}
    return variants


def _digest(environment: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")}
    run = subprocess.run([sys.executable, "-c", DIGEST, str(Path(__file__).parent)], env={**env, **environment},
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout.strip()


def test_the_output_does_not_depend_on_the_cpus_simd_or_blas_kernels():
    """What made a bag recorded on an AVX-512 machine one code off on an AVX2 one: results of
    numpy's SIMD kernels and of BLAS differ in their last bit from CPU to CPU. The simulator
    avoids every such result (``deepsync.frontend.portable``), so the output under every
    other kernel this machine offers is the same, bit for bit."""
    variants = simd_variants()
    if not variants:
        pytest.skip(f"numpy has no run-time kernels to switch on this {platform.machine()} CPU")
    expected = _digest({})
    for name, environment in variants.items():
        assert _digest(environment) == expected, f"{name} ({json.dumps(environment)}) changed the output"


def test_the_digest_check_would_see_a_cpu_dependent_result():
    """The check above has teeth: a plain complex product of single-precision arrays, as the
    simulator made before, rounds differently under numpy's baseline kernels on this machine
    (its AVX2 kernel fuses a*b - c*d into one rounding)."""
    from numpy.core._multiarray_umath import __cpu_features__

    variants = simd_variants()
    if platform.machine() != "x86_64" or not (__cpu_features__.get("FMA3") and __cpu_features__.get("AVX2")):
        pytest.skip("x86-64 with AVX2 and FMA only: elsewhere numpy's baseline kernels already fuse (arm64) "
                    "or there is no fused kernel to switch off")
    probe = ("import hashlib, numpy as np; r = np.random.default_rng(0); "
             "a = (r.standard_normal(1000) + 1j * r.standard_normal(1000)).astype(np.complex64); "
             "print(hashlib.sha256((a * a[::-1]).tobytes()).hexdigest())")
    runs = [subprocess.run([sys.executable, "-c", probe], env={**os.environ, **env}, capture_output=True,
                           text=True, check=True).stdout for env in ({}, variants["numpy baseline kernels"])]
    assert runs[0] != runs[1]
