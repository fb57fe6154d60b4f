"""Sync-code SNR per frame in the ADC domain, and how it scales with load, bandwidth and power.

Definition (per 10 ms frame, over the 276-sample code window at the true arrival): the energy
of the expected sync response (received RE power x template x video gain, mean removed)
divided by the energy of everything else in the window (data self-mixing, neighbouring
symbols, noise, quantisation; mean removed). One cell, one line-of-sight path, the default
front end and ADC; the reported value is the ratio of the summed energies over all frames.

Run:  .venv/bin/python benchmarks/detection/sync_snr.py  [--frames 60]
Writes docs/results/sync_snr.json and docs/results/sync_snr.png.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from deepsync.frontend.channel import Emitter, FixedChannel, Paths  # noqa: E402
from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.simulator import EnvelopeSimulator, SimulationStats  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds  # noqa: E402
from deepsync.lte.cell import CellConfig  # noqa: E402
from deepsync.types import FRAME_SECONDS  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
PCI = 301
DELAY_S = 1.5e-6  # 450 m
EIRP_PER_RE_W = 10 ** ((61 - 30) / 10) / 600  # a 61 dBm, 10 MHz macro sector, per RE


def measure(bandwidth: float, load: float, re_power_dbm: float, frames: int, config: FrontendConfig) -> dict:
    """SNR of one configuration; ``re_power_dbm`` is the received power per RE at the antenna."""
    gain = math.sqrt(10 ** ((re_power_dbm - 30) / 10) / EIRP_PER_RE_W)
    emitter = Emitter(CellConfig(pci=PCI, bandwidth_mhz=bandwidth, load=load), 2115e6, EIRP_PER_RE_W, 0.0, 0.0, "A")
    sim = EnvelopeSimulator([emitter], FixedChannel(Paths([DELAY_S], [gain], [0.0])), config, seed=11)
    stats = SimulationStats()
    seconds = (frames + 2) * FRAME_SECONDS
    codes = np.concatenate([c.samples for c in sim.stream(seconds, stats=stats)])
    volts = codes * config.volts_per_code
    templates = SyncTemplates(config)
    signal_energy = noise_energy = 0.0
    for k in range(1, frames + 1):
        arrival = float(sim.sample_index(k * FRAME_SECONDS + sync_code_offset_seconds() + DELAY_S))
        start = int(np.floor(arrival))
        window = volts[start : start + templates.length]
        expected = templates.template(PCI, 0, arrival - start) * 10 ** ((re_power_dbm - 30) / 10)
        expected *= 10 ** (stats.gain_db / 20)
        expected -= expected.mean()
        residual = window - window.mean() - expected
        signal_energy += float(np.sum(expected**2))
        noise_energy += float(np.sum(residual**2))
    return {
        "bandwidth_mhz": bandwidth,
        "load": load,
        "re_power_dbm": re_power_dbm,
        "diode_power_dbm": stats.diode_power_dbm,
        "snr_db": 10 * math.log10(signal_energy / noise_energy),
        "frames": frames,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    config = FrontendConfig()
    strong = -90.0  # dBm per RE: -62 dBm for a loaded 10 MHz carrier, -32 dBm at the diode

    runs = {
        "load (10 MHz)": [(10, load, strong) for load in (0.1, 0.25, 0.5, 0.75, 1.0)],
        "bandwidth (full load)": [(bw, 1.0, strong) for bw in (1.4, 3, 5, 10, 15, 20)],
        "received power (10 MHz, full load)": [(10, 1.0, p) for p in (-125, -120, -115, -110, -105, -100, -95, -90)],
    }
    results = {}
    with tqdm(total=sum(len(v) for v in runs.values()), desc="sync SNR") as bar:
        for name, points in runs.items():
            results[name] = []
            for bandwidth, load, power in points:
                results[name].append(measure(bandwidth, load, power, args.frames, config))
                bar.update()

    for name, rows in results.items():
        print(f"\n{name}:")
        for r in rows:
            print(f"  {r['bandwidth_mhz']:4g} MHz  load {r['load']:.2f}  {r['re_power_dbm']:6.1f} dBm/RE "
                  f"(diode {r['diode_power_dbm']:6.1f} dBm)  ->  sync SNR {r['snr_db']:6.1f} dB per frame")

    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "sync_snr.json").write_text(json.dumps({"definition": __doc__.split("\n\n")[1], **results}, indent=2))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, (name, rows), key, label in zip(
        axes, results.items(), ("load", "bandwidth_mhz", "re_power_dbm"),
        ("PDSCH load", "bandwidth (MHz)", "received power per RE (dBm)"),
    ):
        ax.plot([r[key] for r in rows], [r["snr_db"] for r in rows], "o-")
        ax.set_xlabel(label)
        ax.set_ylabel("sync-code SNR per frame (dB)")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT / "sync_snr.png", dpi=120)
    print(f"\nwrote {OUT / 'sync_snr.json'} and {OUT / 'sync_snr.png'}")


if __name__ == "__main__":
    main()
