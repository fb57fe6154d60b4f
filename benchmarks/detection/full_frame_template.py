"""Full-frame templates for known cells: what the CRS adds to detection and timing.

A tower database names the PCIs, so everything a known cell sends the same in every frame is
template: its two sync codes and its port-0 CRS (``SyncTemplates.frame_template``). This
benchmark puts the two side by side on the same stacks, at the same false-alarm rate.

The stacks come from the full simulator (square law, video filter, detector and ADC noise, the
cell's own data): a fully loaded cell (PCI 301) at a swept received power per RE, alone, and
beside another loaded cell on the same carrier (PCI 500, -105 dBm per RE, its codes 2.4 ms
away) whose codes, CRS, data and cross terms are part of what the weak cell is searched in.
Each statistic is a template's circular correlation with the stacked frame at every lag and two
sub-sample phases, in units of its robust spread (the search's z). Three ways to use them:

* **codes, searched**: the cell's two sync codes over all 2 x 19,200 positions, against the
  search's CFAR threshold for 1e-3 false alarms per stack (the known-PCI search today).
* **full frame, searched**: the codes plus the CRS, same positions and threshold (its peak
  alone is reported too, as "full frame, its peak alone"). The CRS comb
  (every 6th subcarrier) repeats the CRS envelope every 21.3 samples, and a symbol is 6 such
  periods long, so in the received envelope the positions one comb period away correlate with
  the template nearly as well as the true one: the peak's position is ambiguous. So when the
  full-frame peak passes, the lock is chosen among the peak and its comb alternatives
  (k x 21.3 samples, k = +-1..6, +-1 lag) by the codes' statistic, and kept only if that choice
  is clear: z_best^2 - z_next^2 > 2 ln(1000) (odds of the runner-up below 1e-3).
* **tracked**: the cell's position known to +-1 sample (a tracked cell), 6 tests, the threshold
  for 1e-3 per stack over them; codes vs full frame. No ambiguity to resolve.

* **Pd**: detected within 1 sample of the true code start. **Comb locks**: passed, but one or
  more comb periods away.
* **Timing**: the lock refined on a 1/16-sample grid of the template (the correlation maximum,
  the ML estimate in white noise), then a parabola; RMSE over stacks where both kinds locked.
* **Pfa**: stacks with no such cell (detector noise alone; the other cell alone at -85 dBm per
  RE), counted at the thresholds of 10 %, 1 % and 0.1 % per stack; tracked, at 50 positions
  per stack.
* **SNR**: the per-frame sync SNR of each power (``sync_snr.py``'s definition), so the gain can be
  read in SNR (what the templates change) as well as in received power (what the range sees;
  below the detector's noise knee the envelope's SNR grows with the square of the power).

Run:  .venv/bin/python benchmarks/detection/full_frame_template.py [--stacks 40] [--bandwidths 5 10 20]
Writes docs/results/full_frame_template.json and docs/results/full_frame_template.png.
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
import scipy.fft  # noqa: E402
from tqdm import tqdm  # noqa: E402

import sync_snr  # noqa: E402
from deepsync.frontend.channel import Emitter, FixedChannel, Paths  # noqa: E402
from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.simulator import EnvelopeSimulator  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds  # noqa: E402
from deepsync.lte.cell import CellConfig  # noqa: E402
from deepsync.numeric import mad_spread, parabolic_peak  # noqa: E402
from deepsync.sync.correlation import correlate, template_spectra  # noqa: E402
from deepsync.sync.search import cfar_threshold  # noqa: E402
from deepsync.types import FRAME_SECONDS  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
WEAK, OTHER = 301, 500
DELAYS_S = (1.3e-6, 2.4e-3)  # the weak cell 390 m away; the other cell's frame 2.4 ms later
SCENARIOS = {"alone": None, "beside a -105 dBm cell": -105.0}  # the other cell's power per RE
OTHER_ALONE_DBM = -85.0
EIRP_PER_RE_W = sync_snr.EIRP_PER_RE_W
N_FRAMES = 10
PFA = 1e-3
FINE = 16  # sub-sample phases of the timing grid
COARSE = np.array([0, FINE // 2])  # the search's two phases (0 and 0.5 sample)
COMB_SAMPLES = 1.92e6 / 90e3  # the CRS comb's period in the envelope
COMB = np.round(COMB_SAMPLES * np.arange(-6, 7)).astype(int)  # the peak (k = 0) and its alternatives
TRACK_LAGS = np.arange(-1, 2)
TRACK_POSITIONS = 50  # per noise stack, for the tracked false-alarm rate
PFA_RATES = (1e-1, 1e-2, 1e-3)
KINDS = ("codes", "full frame")
DETECTORS = ("codes, searched", "full frame, searched", "codes, tracked", "full frame, tracked", "full frame, its peak alone")
POWER_GRID = {5: np.arange(-120.0, -97.9, 2.0), 10: np.arange(-122.0, -99.9, 2.0), 20: np.arange(-124.0, -101.9, 2.0)}


def unit_templates(templates: SyncTemplates, bandwidth: float, pci: int = WEAK) -> dict[str, np.ndarray]:
    """(FINE, frame) unit-norm templates of a cell at 1/FINE-sample phases, per kind."""
    phases = np.arange(FINE) / FINE
    full = templates.frame_template(pci, bandwidth, phases)
    codes = np.zeros_like(full)
    for subframe, start in ((0, 0), (5, full.shape[1] // 2)):
        part = templates.template(pci, subframe, phases)
        codes[:, start : start + part.shape[1]] = part - part.mean(axis=1, keepdims=True)
    return {kind: t / np.linalg.norm(t, axis=1, keepdims=True) for kind, t in zip(KINDS, (codes, full))}


def simulate(bandwidth: float, cells: list[tuple[int, float, float]], stacks: int, seed: int,
             config: FrontendConfig) -> tuple[np.ndarray, float]:
    """(stacks, frame) stacked frames of ``cells`` (PCI, dBm per RE, delay) and where the first
    one's subframe-0 code starts (samples, within the frame)."""
    frame = round(config.adc_rate_hz * FRAME_SECONDS)
    emitters = [Emitter(CellConfig(pci=pci, bandwidth_mhz=bandwidth, load=1.0), 2115e6, EIRP_PER_RE_W, 0.0, 0.0, str(pci))
                for pci, _, _ in cells]
    paths = [Paths([delay], [math.sqrt(10 ** ((dbm - 30) / 10) / EIRP_PER_RE_W)], [0.0]) for _, dbm, delay in cells]
    sim = EnvelopeSimulator(emitters, FixedChannel(paths), config, seed=seed)
    volts = np.concatenate([c.samples for c in sim.stream(stacks * N_FRAMES * FRAME_SECONDS, workers=2)])
    frames = volts[: stacks * N_FRAMES * frame].astype(np.float64).reshape(stacks, N_FRAMES, frame)
    code = float(sim.sample_index(sync_code_offset_seconds() + cells[0][2])) % frame
    return frames.mean(axis=1), code


def statistics(stacked: np.ndarray, spectra: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per kind: (FINE, frame) correlations of a stacked frame with the templates, and their z
    (spread measured on the search's two phases)."""
    spectrum = scipy.fft.rfft(stacked - stacked.mean())
    out = {}
    for kind, s in spectra.items():
        c = correlate(spectrum, s, len(stacked)).astype(np.float64)
        out[kind] = c, c / mad_spread(c[COARSE], keepdims=True, centre=0.0)
    return out


def refine(c: np.ndarray, lag: int) -> float:
    """Code start from the correlations on a 1/FINE grid around a whole-sample ``lag``."""
    frame = c.shape[1]
    fine = c[:, (lag + np.arange(-1, 2)) % frame].T.ravel()  # 3 lags x FINE phases, in time order
    best = int(np.argmax(fine))
    return lag - 1 + (best + parabolic_peak(fine, best)) / FINE


def best_near(z: np.ndarray, lags: np.ndarray) -> tuple[float, int]:
    """Highest z of the search's phases over ``lags`` (any shape), and its lag."""
    frame = z.shape[1]
    values = z[COARSE][:, lags % frame]
    index = np.unravel_index(np.argmax(values), values.shape)
    return float(values[index]), int(lags[index[1:]] % frame)


def detect(stats: dict, threshold: dict[str, float], predicted: int | None) -> dict[str, int | None]:
    """Per detector, the whole-sample lag it locks on (None: nothing passed)."""
    out: dict[str, int | None] = {}
    for kind in KINDS:
        z = stats[kind][1][COARSE]
        row, lag = np.unravel_index(np.argmax(z), z.shape)
        out[f"{kind}, searched"] = int(lag) if z[row, lag] > threshold["searched"] else None
        if predicted is not None:
            value, lag = best_near(stats[kind][1], predicted + TRACK_LAGS)
            out[f"{kind}, tracked"] = lag if value > threshold["tracked"] else None
    peak = out["full frame, searched"]
    out["full frame, its peak alone"] = peak
    if peak is not None:  # which comb period: the codes decide, if clearly
        votes = sorted((best_near(stats["codes"][1], peak + k + TRACK_LAGS) for k in COMB), reverse=True)
        clear = votes[0][0] ** 2 - votes[1][0] ** 2 > 2 * math.log(1 / PFA)
        out["full frame, searched"] = best_near(stats["full frame"][1], votes[0][1] + TRACK_LAGS)[1] if clear else None
    return out


def wrapped(x: float, frame: int) -> float:
    return (x + frame / 2) % frame - frame / 2


def curves(bandwidth: float, stacks: int, config: FrontendConfig, templates: SyncTemplates) -> dict:
    kinds = unit_templates(templates, bandwidth)
    frame = kinds["codes"].shape[1]
    spectra = {kind: template_spectra(t, frame) for kind, t in kinds.items()}
    threshold = {"searched": cfar_threshold(PFA, len(COARSE) * frame),
                 "tracked": cfar_threshold(PFA, len(COARSE) * len(TRACK_LAGS))}
    grid = POWER_GRID[int(bandwidth)]
    snr = [sync_snr.measure(bandwidth, 1.0, float(dbm), 20, config)["snr_db"] for dbm in grid]
    scenarios = {}
    for scenario, other_dbm in SCENARIOS.items():
        rows = []
        for dbm in tqdm(grid, desc=f"{bandwidth:g} MHz, {scenario}"):
            cells = [(WEAK, dbm, DELAYS_S[0])] + ([] if other_dbm is None else [(OTHER, other_dbm, DELAYS_S[1])])
            stacked, truth = simulate(bandwidth, cells, stacks, seed=int(-10 * dbm), config=config)
            row = {"re_power_dbm": float(dbm), **{d: {"found": 0, "comb_locks": 0, "other_false": 0} for d in DETECTORS}}
            errors: dict[str, list[float]] = {d: [] for d in DETECTORS}
            for s in stacked:
                stats = statistics(s, spectra)
                locks = detect(stats, threshold, int(round(truth)))
                for detector, lag in locks.items():
                    if lag is None:
                        continue
                    error = wrapped(refine(stats[detector.split(",")[0]][0], lag) - truth, frame)
                    on_comb = abs(error) > 1 and abs(error) < 6.5 * COMB_SAMPLES
                    row[detector]["found" if abs(error) <= 1 else "comb_locks" if on_comb else "other_false"] += 1
                    errors[detector].append(error)
                for mode in ("searched", "tracked"):  # timing over the stacks both kinds locked on
                    pair = [f"{kind}, {mode}" for kind in KINDS]
                    if all(locks[d] is not None and abs(errors[d][-1]) <= 1 for d in pair):
                        for d in pair:
                            row[d].setdefault("common", []).append(errors[d][-1])
            for d in DETECTORS:
                common = np.array(row[d].pop("common", []))
                row[d]["pd"] = row[d].pop("found") / stacks
                row[d]["timing_rmse"] = float(np.sqrt(np.mean(common**2))) if common.size else None
                row[d]["timing_stacks"] = int(common.size)
            rows.append(row)
        scenarios[scenario] = {"points": rows, "pd90_dbm": {d: crossing(grid, [r[d]["pd"] for r in rows]) for d in DETECTORS},
                               "pd90_snr_db": {d: crossing(np.array(snr), [r[d]["pd"] for r in rows]) for d in DETECTORS}}
    return {"bandwidth_mhz": bandwidth, "thresholds_z": threshold, "snr_db": dict(zip(map(float, grid), snr)),
            "template_energy_gain_db": energy_gain_db(templates, bandwidth), "scenarios": scenarios,
            "false_alarms": false_alarms(bandwidth, stacks * 3, config, spectra, frame)}


def false_alarms(bandwidth: float, stacks: int, config: FrontendConfig, spectra: dict, frame: int) -> dict:
    """Where the absent weak cell's statistic passes the threshold of each rate: searched, per
    stack; tracked, per predicted position."""
    rng = np.random.default_rng(5)
    out = {}
    # the simulator needs an emitter: noise alone is a cell 200 dB below the detector's noise
    for name, dbm in (("noise", -300.0), ("other cell", OTHER_ALONE_DBM)):
        stacked, _ = simulate(bandwidth, [(OTHER, dbm, DELAYS_S[1])], stacks, seed=7, config=config)
        peaks: dict[str, list[float]] = {f"{kind}, {mode}": [] for mode in ("searched", "tracked") for kind in KINDS}
        for s in stacked:
            stats = statistics(s, spectra)
            for kind in KINDS:
                z = stats[kind][1]
                peaks[f"{kind}, searched"].append(float(z[COARSE].max()))
                peaks[f"{kind}, tracked"] += [best_near(z, p + TRACK_LAGS)[0] for p in rng.integers(0, frame, TRACK_POSITIONS)]
        out[name] = {}
        for detector, values in peaks.items():
            tests = len(COARSE) * (frame if detector.endswith("searched") else len(TRACK_LAGS))
            out[name][detector] = {"trials": len(values),
                                   **{f"{rate:g}": float(np.mean(np.array(values) > cfar_threshold(rate, tests)))
                                      for rate in PFA_RATES}}
    return out


def energy_gain_db(templates: SyncTemplates, bandwidth: float) -> float:
    """Matched-filter energy of the full frame over the codes alone (white-noise approximation)."""
    full = templates.frame_template(WEAK, bandwidth, [0.0])[0]
    codes = sum(np.sum((t - t.mean()) ** 2) for t in (templates.template(WEAK, s, 0.0) for s in (0, 5)))
    return float(10 * np.log10(np.sum(full**2) / codes))


def crossing(grid: np.ndarray, pd: list[float], target: float = 0.9) -> float | None:
    """Lowest x from which Pd stays at or above ``target`` (linear between grid points)."""
    pd = np.asarray(pd)
    below = np.flatnonzero(pd < target)
    if not below.size:
        return float(grid[0])
    k = below[-1]
    if k == len(pd) - 1:
        return None
    return float(grid[k] + (target - pd[k]) / (pd[k + 1] - pd[k]) * (grid[k + 1] - grid[k]))


def plot(results: list[dict], path: Path) -> None:
    fig, axes = plt.subplots(len(SCENARIOS), 2, figsize=(12, 4.2 * len(SCENARIOS)), squeeze=False)
    styles = {"codes, searched": ":", "full frame, searched": "-.", "codes, tracked": "--", "full frame, tracked": "-"}
    for ax_row, scenario in zip(axes, SCENARIOS):
        for result, colour in zip(results, ("C0", "C1", "C2")):
            points = result["scenarios"][scenario]["points"]
            powers = [p["re_power_dbm"] for p in points]
            for detector, style in styles.items():
                label = f"{result['bandwidth_mhz']:g} MHz, {detector}"
                ax_row[0].plot(powers, [p[detector]["pd"] for p in points], style, color=colour, label=label)
                if detector.endswith("tracked"):
                    rmse = [np.nan if p[detector]["timing_rmse"] is None else p[detector]["timing_rmse"] for p in points]
                    ax_row[1].semilogy(powers, rmse, style, color=colour, marker="o", label=label)
        ax_row[0].axhline(0.9, color="grey", lw=0.8)
        ax_row[0].set_ylabel(f"Pd ({N_FRAMES}-frame stack, Pfa 1e-3)")
        ax_row[1].set_ylabel("timing RMSE, tracked (samples)")
        for ax in ax_row:
            ax.set_title(f"known cell {scenario}", fontsize=9)
            ax.set_xlabel("received power per RE (dBm)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    fig.suptitle("Sync codes alone vs the full frame (codes + CRS)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def report(results: list[dict]) -> None:
    def number(x: float | None, unit: str) -> str:
        return "never" if x is None else f"{x:.1f} {unit}"

    for r in results:
        print(f"\n{r['bandwidth_mhz']:g} MHz: full-frame template energy +{r['template_energy_gain_db']:.1f} dB over the codes")
        for scenario, result in r["scenarios"].items():
            print(f"  {scenario}: Pd 90 % from")
            for d in DETECTORS:
                print(f"    {d:22s} {number(result['pd90_dbm'][d], 'dBm/RE'):>14s}  (SNR {number(result['pd90_snr_db'][d], 'dB per frame')})")
            print("    dBm/RE   Pd: codes / full searched, codes / full tracked, full peak alone   "
                  "comb locks: full searched (its peak alone)   RMSE tracked codes / full")
            for p in r["scenarios"][scenario]["points"]:
                pd = " / ".join(f"{p[d]['pd']:.2f}" for d in DETECTORS)
                rmse = " / ".join("-" if p[d]["timing_rmse"] is None else f"{p[d]['timing_rmse']:.3f}"
                                  for d in ("codes, tracked", "full frame, tracked"))
                locks = f"{p['full frame, searched']['comb_locks']} ({p['full frame, its peak alone']['comb_locks']})"
                print(f"    {p['re_power_dbm']:6.1f}   {pd}          {locks:10s}                              {rmse}")
        for name, rates in r["false_alarms"].items():
            print(f"  false alarms, {name}: measured rate at the 10 % / 1 % / 0.1 % thresholds")
            for d, counts in rates.items():
                print(f"    {d:22s} " + " / ".join(f"{counts[f'{rate:g}']:.4f}" for rate in PFA_RATES)
                      + f"   ({counts['trials']} trials)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stacks", type=int, default=40, help="10-frame stacks per power point")
    parser.add_argument("--bandwidths", type=float, nargs="+", default=[5, 10, 20], choices=[5, 10, 20])
    args = parser.parse_args()
    config = FrontendConfig()
    templates = SyncTemplates(config)
    results = [curves(bw, args.stacks, config, templates) for bw in args.bandwidths]
    report(results)
    OUT.mkdir(parents=True, exist_ok=True)
    document = {"definition": __doc__.split("\n\n", 1)[1].rsplit("\n\nRun:", 1)[0], "stacks_per_point": args.stacks,
                "frames_per_stack": N_FRAMES, "results": results}
    (OUT / "full_frame_template.json").write_text(json.dumps(document, indent=2))
    plot(results, OUT / "full_frame_template.png")
    print(f"\nwrote {OUT / 'full_frame_template.json'} and {OUT / 'full_frame_template.png'}")


if __name__ == "__main__":
    main()
