"""Can the envelope tell the first path from the multipath behind it? A smeared-template test.

The stacked envelope of a fading channel is, on average over the fading, the code's envelope
convolved with the channel's power-delay profile (the cross terms between taps average out):
E|h * s|^2 = sum_k P_k |s(t - tau_k)|^2. If that held per stack, fitting the code template
convolved with an exponential profile (decay ``beta`` samples, the onset a free delay) would
find the first path where ML on the plain template finds the envelope's centre, late by the
multipath. This benchmark asks whether the data support it, on the timing test split
(``data/timing/test``, true first-path offsets, TDL-A..E with 38.901 delay spreads):

* for each ``beta`` on a grid, ML with the smeared template (``estimate_ml``, the same windows,
  noise spectrum and margin): the median signed and absolute error against the first path,
  and how much better (dB of fitted SNR) it fits than the plain template (beta = 0);
* "fitted": per example the beta whose template fits best, the ML answer to the question.

Examples at -8 dB per frame or more (ML above its threshold, so what is measured is bias, not
wrong lobes), 10 frames. NLOS = TDL-A/B/C, LOS = TDL-D/E.

Run:  .venv/bin/python benchmarks/timing/nlos_smear.py   (the test split comes from
``deepsync train --config config/timing/timing_net.yaml``, which makes the data first)
Writes docs/results/timing_network/nlos_smear.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import scipy.signal
from tqdm import tqdm

from deepsync.timing.estimators import estimate_ml, noise_psd
from deepsync.training.dataset import LOS_PROFILES, PROFILES, load_split

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "docs" / "results" / "timing_network" / "nlos_smear.json"
BETAS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)  # decay of the exponential profile, samples
MIN_SNR_DB = -8.0
FRAMES = 10


def smeared(template: np.ndarray, beta: float) -> np.ndarray:
    """The template convolved with a causal exponential of decay ``beta`` samples (unit gain)."""
    if beta == 0:
        return template
    decay = np.exp(-1 / beta)
    return scipy.signal.lfilter([1 - decay], [1, -decay], template)


def measure(data: dict[str, np.ndarray], progress: bool) -> dict[str, np.ndarray]:
    """Per kept example: its LOS flag, and per beta the error (samples) and the fitted SNR (dB)."""
    keep = np.flatnonzero(data["snr_db"] >= MIN_SNR_DB)
    los, errors, snrs = [], [], []
    for i in tqdm(keep, desc="examples", disable=not progress):
        windows = data["windows"][i, :FRAMES].astype(np.float64)
        template = data["template"][i].astype(np.float64)
        margin = (windows.shape[1] - template.size) // 2
        psd = noise_psd(windows)
        try:
            fits = [estimate_ml(windows, smeared(template, beta), margin, psd) for beta in BETAS]
        except ValueError:  # a window ML cannot time says so; it is left out
            continue
        los.append(PROFILES[int(data["profile"][i])] in LOS_PROFILES)
        errors.append([f.offset - float(data["offset"][i]) for f in fits])
        snrs.append([f.snr_db for f in fits])
    return {"los": np.array(los), "errors": np.array(errors), "snr_db": np.array(snrs)}


def summary(errors: np.ndarray, gain_db: np.ndarray | None = None) -> dict:
    row = {"median_error": float(np.median(errors)), "median_abs_error": float(np.median(np.abs(errors)))}
    if gain_db is not None:
        row["median_fit_gain_db"] = float(np.median(gain_db))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(REPO / "data" / "timing"))
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args()
    measured = measure(load_split(Path(args.data), "test"), progress=not args.quiet)
    result = {"examples": {}, "min_snr_db": MIN_SNR_DB, "frames": FRAMES, "betas": {}, "fitted": {}}
    for name, mask in (("nlos", ~measured["los"]), ("los", measured["los"])):
        errors, snrs = measured["errors"][mask], measured["snr_db"][mask]
        result["examples"][name] = int(mask.sum())
        result["betas"][name] = {str(b): summary(errors[:, k], snrs[:, k] - snrs[:, 0]) for k, b in enumerate(BETAS)}
        best = np.argmax(snrs, axis=1)
        result["fitted"][name] = {**summary(errors[np.arange(len(best)), best]),
                                  "beta_chosen_share": {str(b): float(np.mean(best == k)) for k, b in enumerate(BETAS)}}
    print(f"{result['examples']} examples at >= {MIN_SNR_DB:g} dB per frame, {FRAMES} frames; errors vs the first path "
          "(samples): median signed / median |e|; fit gain over the plain template (dB, median)")
    for name in ("nlos", "los"):
        print(f"  {name.upper():4s} " + "  ".join(
            f"b={b:g}: {r['median_error']:+.3f}/{r['median_abs_error']:.3f}/{r['median_fit_gain_db']:+.2f}"
            for b, r in zip(BETAS, result["betas"][name].values())))
        fitted = result["fitted"][name]
        print(f"       fitted beta: {fitted['median_error']:+.3f}/{fitted['median_abs_error']:.3f}, chosen "
              + ", ".join(f"{b}: {100 * s:.0f}%" for b, s in fitted["beta_chosen_share"].items()))
    OUT.write_text(json.dumps(result, indent=1))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
