"""Cell search Monte-Carlo: detection probability, false alarms and PCI confusion vs SNR.

Interference is real: the envelope of a simulated, fully loaded 10 MHz cell (its data's square
law products, CRS and control channels, detector and ADC noise), cut into 10 ms frames. Each
trial takes N consecutive frames of it, adds the sync codes of a random PCI at a random,
sub-sample position, scaled to a given per-frame sync SNR (energy of the zero-mean code over
its 276-sample window / interference energy in such a window, as in sync_snr.py), and runs the
search on the stacked frames, blind (504 PCIs) and with a tower database of the true PCI and
19 others (the resident cell among them). The resident cell's own codes are a real cell: detections there are not false.

* Pd: a detection within 1 sample of the code (modulo the 5 ms the PSS repeats with).
* Identity: that detection names the true PCI; N_ID2 / N_ID1 right; true PCI in the candidates.
* Pfa: stacks of interference alone with any detection besides the resident cell.

Run:  .venv/bin/python benchmarks/detection/cell_search.py [--trials 200]
Writes docs/results/cell_search.json and docs/results/cell_search.png.
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
from deepsync.frontend.simulator import EnvelopeSimulator  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds  # noqa: E402
from deepsync.lte.cell import CellConfig  # noqa: E402
from deepsync.sync.search import CellSearch, SearchConfig  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
FRAME = 19200
HALF = FRAME // 2
RESIDENT_PCI = 500
SNR_GRID = {1: np.arange(-10.0, 8.1, 1.5), 5: np.arange(-18.0, 0.1, 1.5),
            10: np.arange(-21.0, -2.9, 1.5), 20: np.arange(-24.0, -5.9, 1.5)}


def interference(seconds: float, config: FrontendConfig) -> tuple[np.ndarray, float]:
    """(frames, 19200) envelope of a loaded 10 MHz cell, and where its own codes sit."""
    cell = Emitter(CellConfig(pci=RESIDENT_PCI, bandwidth_mhz=10, load=1.0), 2115e6, 2e-3, 0.0, 0.0, "R")
    sim = EnvelopeSimulator([cell], FixedChannel(Paths([1e-6], [3e-5], [0.0])), config, seed=21)
    volts = np.concatenate([c.samples for c in sim.stream(seconds, workers=2)]).astype(np.float64)
    frames = volts[: len(volts) // FRAME * FRAME].reshape(-1, FRAME)
    resident = float(sim.sample_index(sync_code_offset_seconds() + 1e-6)) % FRAME
    return frames - frames.mean(), resident


def interference_sigma(frames: np.ndarray, resident: float) -> float:
    """Interference RMS per sample, away from the resident cell's own codes."""
    return float(np.std(frames[:, (np.arange(FRAME) - resident) % HALF > 400]))


class TowerDatabases:
    """The known-PCI search of a trial: a tower database of the true PCI, the resident cell
    and 18 other PCIs (drawn once per true PCI)."""

    def __init__(self, templates: SyncTemplates, rng: np.random.Generator) -> None:
        self.templates, self.rng = templates, rng
        self.searches: dict[int, CellSearch] = {}

    def __call__(self, pci: int) -> CellSearch:
        if pci not in self.searches:
            others = self.rng.choice(np.setdiff1d(np.arange(504), [pci, RESIDENT_PCI]), 18, replace=False)
            self.searches[pci] = CellSearch(self.templates, SearchConfig(), [pci, RESIDENT_PCI, *others.tolist()])
        return self.searches[pci]


def near(position: float, target: float, period: int) -> bool:
    d = (position - target) % period
    return min(d, period - d) <= 1.0


def trial(rng, frames, resident, templates, blind, database, pci, n, snr_db, sigma, modes=("blind", "known")):
    """One stack with the codes of ``pci`` (None: interference alone). Per mode ("blind",
    "known"): (hit, PCI right, N_ID2 right, N_ID1 right, PCI in candidates, any false cell)."""
    start = rng.integers(0, len(frames) - n)
    stacked = frames[start : start + n].mean(axis=0)
    offset = rng.uniform(0, FRAME)
    if pci is not None:
        codes = np.zeros(FRAME)
        for subframe, at in ((0, offset), (5, offset + HALF)):
            whole = int(np.floor(at))
            shape = templates.template(pci, subframe, at - whole)
            codes[(whole + np.arange(len(shape))) % FRAME] += shape - shape.mean()
        energy = np.sum((templates.template(pci, 0, offset % 1) - templates.template(pci, 0, offset % 1).mean()) ** 2)
        amplitude = math.sqrt(10 ** (snr_db / 10) * len(shape) * sigma**2 / energy)
        stacked = stacked + amplitude * codes
    outcome = {}
    for mode in modes:
        search = blind if mode == "blind" else database(RESIDENT_PCI if pci is None else pci)
        found = search.search(stacked)
        hit = [d for d in found if pci is not None and near(d.frame_offset + d.fraction, offset, HALF)]
        false = [d for d in found if d not in hit and not near(d.frame_offset + d.fraction, resident, HALF)]
        d = hit[0] if hit else None
        outcome[mode] = (
            bool(hit),
            bool(d and d.pci == pci),
            bool(d and d.pci % 3 == pci % 3),
            bool(d and d.pci // 3 == pci // 3),
            bool(d and pci in [c.pci for c in d.candidates]),
            bool(false),
        )
    return outcome


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=4.0, help="interference to simulate")
    args = parser.parse_args()
    rng = np.random.default_rng(2026)
    config = FrontendConfig()
    templates = SyncTemplates(config)
    print(f"simulating {args.seconds:g} s of interference ...")
    frames, resident = interference(args.seconds, config)
    sigma = interference_sigma(frames, resident)

    blind = CellSearch(templates, SearchConfig())
    database = TowerDatabases(templates, rng)
    results: dict = {"definition": __doc__.split("\n\n")[1], "trials": args.trials, "curves": {}}
    pcis = rng.choice(np.setdiff1d(np.arange(504), [RESIDENT_PCI]), 40, replace=False)
    total = sum(len(v) for v in SNR_GRID.values()) * args.trials + 4 * args.trials
    with tqdm(total=total, desc="cell search") as bar:
        for n, grid in SNR_GRID.items():
            curve = []
            for snr in grid:
                tally = {m: np.zeros(6) for m in ("blind", "known")}
                for _ in range(args.trials):
                    out = trial(rng, frames, resident, templates, blind, database, int(rng.choice(pcis)), n, snr, sigma)
                    for m in tally:
                        tally[m] += out[m]
                    bar.update()
                row = {"snr_db": float(snr)}
                for m, t in tally.items():
                    p = t / args.trials
                    row[m] = {"pd": p[0], "pci": p[1], "n_id2": p[2], "n_id1": p[3], "in_candidates": p[4],
                              "false_in_signal": p[5]}
                curve.append(row)
            false_alarms = 0
            for _ in range(args.trials):
                out = trial(rng, frames, resident, templates, blind, database, None, n, 0.0, sigma)
                false_alarms += out["blind"][5]
                bar.update()
            results["curves"][str(n)] = {"points": curve, "pfa_blind": false_alarms / args.trials}

    print(f"\nper-frame sync SNR needed (interference: one loaded 10 MHz cell; {args.trials} trials/point)")
    for n, data in results["curves"].items():
        points = data["points"]
        for mode in ("blind", "known"):
            snrs = [p["snr_db"] for p in points]
            pd = [p[mode]["pd"] for p in points]
            needed = next((s for s, v in zip(snrs, pd) if v >= 0.99), math.nan)
            data[f"snr_for_pd99_{mode}"] = needed
        print(f"  {n:2s} frames: Pd>=99% at {data['snr_for_pd99_blind']:6.1f} dB blind, "
              f"{data['snr_for_pd99_known']:6.1f} dB with a tower DB; false-alarm rate per stack "
              f"(blind, noise only) {data['pfa_blind']:.3f}")
    print("\nidentity at the detected code, blind (504 PCIs), 10 frames:")
    for p in results["curves"]["10"]["points"]:
        b, k = p["blind"], p["known"]
        print(f"  {p['snr_db']:6.1f} dB  Pd {b['pd']:.2f}  PCI {b['pci']:.2f}  N_ID2 {b['n_id2']:.2f}  "
              f"N_ID1 {b['n_id1']:.2f}  in top-8 {b['in_candidates']:.2f}   | DB: Pd {k['pd']:.2f} PCI {k['pci']:.2f}")

    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "cell_search.json").write_text(json.dumps(results, indent=2))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for n, data in results["curves"].items():
        snrs = [p["snr_db"] for p in data["points"]]
        for mode, style in (("blind", "-"), ("known", "--")):
            axes[0].plot(snrs, [p[mode]["pd"] for p in data["points"]], style, label=f"{n} frames, {mode}")
        axes[1].plot(snrs, [p["blind"]["pci"] for p in data["points"]], "-", label=f"{n} frames: PCI")
        axes[1].plot(snrs, [p["blind"]["n_id2"] for p in data["points"]], ":", label=f"{n} frames: N_ID2")
        axes[2].plot(snrs, [p["known"]["pci"] for p in data["points"]], "-", label=f"{n} frames")
    for ax, title in zip(axes, ("detection probability (solid blind, dashed tower DB)",
                                "blind identity at the detected code", "identity with a 20-PCI tower DB")):
        ax.set_xlabel("per-frame sync SNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].axhline(0.99, color="grey", lw=0.5)
    fig.tight_layout()
    fig.savefig(OUT / "cell_search.png", dpi=120)
    print(f"wrote {OUT / 'cell_search.json'} and {OUT / 'cell_search.png'}")


if __name__ == "__main__":
    main()
