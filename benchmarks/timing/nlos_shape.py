"""Can a cell's NLOS pull be told from the shape of its full-frame correlation?

``ml_frame`` times a known cell's whole frame to within its Cramer-Rao bound, but on NLOS
channels the envelope's peak sits late of the first path (the label): on the network's test
split about +0.25 samples (40 m) on TDL-A/B/C, against about 0 on TDL-D/E. A network fed whole
frames could remove that pull only if the frame shows it. What the frame holds of one cell is its
correlation with the cell's known frame (the matched filter of a known template), so this asks
the question of that correlation: its shape at half-sample steps within +-8 samples of
``ml_frame``'s fit, normalised by its value at the fit, plus the cell's SNR and bandwidth.

* a classifier (small MLP) tells NLOS (TDL-A/B/C) from LOS (TDL-D/E) by that shape; compared
  with always guessing the commoner class;
* a regression (ridge, and a small MLP with the Huber loss) learns the correction to
  ``ml_frame``'s offset, scored on NLOS and LOS cells apart;
* an oracle regression given the channel's profile and delay spread (what a cell's shape would
  have to reveal) bounds what such a correction could give.

Single cells (no co-sited pairs), 10 frames, examples where ``ml_frame`` is within a sample of
the true first path (its wrong lobes are another question). Training: the first 16 shards of
the dataset's training split made again with their mean frames (``data/timing_nlos``, 4096
examples, about 3 minutes on 2 cores, resumable); test: ``benchmarks/timing/split_variants.py ml_frame``'s
test split (made here if missing).

Run:  .venv/bin/python benchmarks/timing/nlos_shape.py [--workers 2]
Writes docs/results/timing_network/nlos_shape.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.fft
import torch
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from deepsync.eval.timing import time_by_frame
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates, known_frame
from deepsync.training.dataset import LOS_PROFILES, PROFILES, generate, load_split
from deepsync.training.train import load_run_config
from split_variants import CONFIG, ML_FRAME as TEST_FRAMES, VARIANTS  # the test split with mean frames

REPO = Path(__file__).resolve().parents[2]
TRAIN_DATA = REPO / "data" / "timing_nlos"
TEST_DATA = VARIANTS["ml_frame"].data
TRAIN_SHARDS = 16
OUT = REPO / "docs" / "results" / "timing_network" / "nlos_shape.json"
FRAMES = 10
LAGS = np.arange(-16, 17) / 2  # samples either side of the fit at which the shape is read
BANDWIDTHS_MHZ = (1.4, 3.0, 5.0, 10.0, 15.0, 20.0)
SEED = 0


def correlation_shapes(data: dict[str, np.ndarray], offsets: np.ndarray) -> np.ndarray:
    """(examples, LAGS) correlation of each mean frame with its cell's known frame at the fitted
    code start + LAGS, over its value at the fit (NaN where ml_frame gave nothing)."""
    templates, conj_spectra = SyncTemplates(FrontendConfig()), {}
    shapes = np.full((len(offsets), len(LAGS)), np.nan)
    for i in tqdm(np.flatnonzero(np.isfinite(offsets)), desc="shapes"):
        key = (int(data["pci"][i]), float(data["bandwidth_mhz"][i]))
        if key not in conj_spectra:
            conj_spectra[key] = np.conj(scipy.fft.rfft(known_frame(templates, *key)))
        frame = data[f"frame_{FRAMES}"][i].astype(np.float64)
        cross = scipy.fft.rfft(frame - frame.mean()) * conj_spectra[key]
        omega = 2 * np.pi * np.arange(cross.size) / frame.size
        # the mean frame holds the code frame_delay later than the toa's time base (sample 0: coarse start)
        fitted = offsets[i] + float(data[f"frame_delay_{FRAMES}"][i])
        values = np.real(np.exp(1j * np.outer(fitted + LAGS, omega)) @ cross)
        shapes[i] = values / values[len(LAGS) // 2]
    return shapes


def load(root: Path, split: str) -> dict[str, np.ndarray]:
    """A split's single cells with ml_frame's offset (``toa``), its error and the shape features."""
    data = load_split(root, split)
    single = data["cosited_pci"] < 0
    data = {k: v[single] for k, v in data.items() if isinstance(v, np.ndarray) and v.shape[:1] == single.shape}
    offsets = np.array([toa for toa, _, _ in time_by_frame(data, FRAMES)])
    data["error"] = offsets - data["offset"]
    data["shape"] = correlation_shapes(data, offsets)
    data["nlos"] = np.array([PROFILES[p] not in LOS_PROFILES for p in data["profile"]])
    return data


def within_a_sample(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The cells ml_frame timed within a sample of the truth (its main lobe), with a shape."""
    kept = np.isfinite(data["error"]) & (np.abs(data["error"]) < 1) & np.all(np.isfinite(data["shape"]), axis=1)
    return {k: v[kept] for k, v in data.items()}


def cell_features(data: dict[str, np.ndarray]) -> np.ndarray:
    """What a timing stage knows of every cell: its bandwidth (one-hot) and SNR."""
    bandwidth = np.stack([np.isclose(data["bandwidth_mhz"], b) for b in BANDWIDTHS_MHZ], axis=1)
    return np.hstack([bandwidth, np.clip(data["snr_db"], -30, 15)[:, None] / 10])


def features(data: dict[str, np.ndarray]) -> np.ndarray:
    """The shape, its asymmetry (late minus early), and the cell's features."""
    shape = data["shape"]
    half = len(LAGS) // 2
    asymmetry = shape[:, half + 1 :] - shape[:, :half][:, ::-1]
    return np.hstack([shape, asymmetry, cell_features(data)])


def oracle_features(data: dict[str, np.ndarray]) -> np.ndarray:
    """What the shape would have to reveal, the profile (one-hot) and delay spread, and the cell's features."""
    profile = np.stack([data["profile"] == k for k in range(len(PROFILES))], axis=1)
    return np.hstack([profile, data["delay_spread_ns"][:, None] / 100, cell_features(data)])


def fit_mlp(x: np.ndarray, y: np.ndarray, classify: bool, epochs: int = 300) -> Callable[[np.ndarray], np.ndarray]:
    """A two-layer MLP (32 units) on standardised inputs; returns its prediction function."""
    mean, std = x.mean(axis=0), x.std(axis=0) + 1e-9
    torch.manual_seed(SEED)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 32), torch.nn.ReLU(), torch.nn.Linear(32, 32),
                              torch.nn.ReLU(), torch.nn.Linear(32, 1))
    optimiser = torch.optim.Adam(net.parameters(), 3e-3, weight_decay=1e-2)
    inputs = torch.tensor((x - mean) / std, dtype=torch.float32)
    targets = torch.tensor(y, dtype=torch.float32)
    for _ in range(epochs):
        order = torch.randperm(len(inputs))
        for start in range(0, len(inputs), 128):
            batch = order[start : start + 128]
            out = net(inputs[batch])[:, 0]
            loss = (torch.nn.functional.binary_cross_entropy_with_logits(out, targets[batch]) if classify
                    else torch.nn.functional.huber_loss(out, targets[batch], delta=0.3))
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()

    def predict(z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = net(torch.tensor((z - mean) / std, dtype=torch.float32))[:, 0]
        return (torch.sigmoid(out) if classify else out).numpy()
    return predict


def fit_ridge(x: np.ndarray, y: np.ndarray, penalty: float = 0.1) -> Callable[[np.ndarray], np.ndarray]:
    """Ridge regression with an intercept; returns its prediction function."""
    design = np.hstack([x, np.ones((len(x), 1))])
    weights = np.linalg.solve(design.T @ design + penalty * np.eye(design.shape[1]), design.T @ y)
    return lambda z: np.hstack([z, np.ones((len(z), 1))]) @ weights


def scored(errors: np.ndarray, nlos: np.ndarray) -> dict[str, float]:
    """Median |error| and RMSE (samples) on NLOS and LOS cells."""
    out = {}
    for name, mask in (("nlos", nlos), ("los", ~nlos)):
        out[f"{name}_median_abs"] = float(np.median(np.abs(errors[mask])))
        out[f"{name}_rmse"] = float(np.sqrt(np.mean(errors[mask] ** 2)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    run = load_run_config(CONFIG)
    generate(TRAIN_DATA, {"train": TRAIN_SHARDS}, dataclasses.replace(run.dataset, frame_means=(FRAMES,)),
             args.workers)
    generate(TEST_DATA, {"test": run.training.test_shards}, dataclasses.replace(run.dataset, frame_means=TEST_FRAMES),
             args.workers)
    with threadpool_limits(limits=1):
        train, test = load(TRAIN_DATA, "train"), load(TEST_DATA, "test")
    tr, te = within_a_sample(train), within_a_sample(test)
    result = {"examples": {"train": len(tr["error"]), "test": len(te["error"])},
              "ml_frame": scored(te["error"], te["nlos"]),
              "ml_frame_mean_error": {"nlos": float(np.mean(te["error"][te["nlos"]])),
                                      "los": float(np.mean(te["error"][~te["nlos"]]))}}

    classification = {}
    for low in (-30.0, -15.0, -5.0):
        a, b = tr["snr_db"] >= low, te["snr_db"] >= low
        predict = fit_mlp(features({k: v[a] for k, v in tr.items()}), tr["nlos"][a].astype(np.float32), classify=True)
        guessed = predict(features({k: v[b] for k, v in te.items()})) > 0.5
        share = float(np.mean(te["nlos"][b]))
        classification[f"snr_from_{low:g}_db"] = {
            "test_cells": int(b.sum()), "accuracy": float(np.mean(guessed == te["nlos"][b])),
            "commoner_class_share": max(share, 1 - share)}
    result["nlos_classifier"] = classification

    corrections = {}
    for name, fit, make in (("ridge", fit_ridge, features), ("mlp", lambda x, y: fit_mlp(x, y, False), features),
                            ("oracle_mlp", lambda x, y: fit_mlp(x, y, False), oracle_features)):
        predict = fit(make(tr), -tr["error"])  # the correction: true offset - ml_frame's
        corrections[name] = scored(te["error"] + predict(make(te)), te["nlos"])
    result["corrected"] = corrections
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=1) + "\n")

    print(f"test: {result['examples']['test']} single cells within a sample of the truth "
          f"(train {result['examples']['train']}); ml_frame's mean error: NLOS "
          f"{result['ml_frame_mean_error']['nlos']:+.3f}, LOS {result['ml_frame_mean_error']['los']:+.3f} samples")
    print("NLOS vs LOS from the shape:")
    for key, row in classification.items():
        print(f"  {key:>16s}: accuracy {row['accuracy']:.3f} against {row['commoner_class_share']:.3f} "
              f"by always guessing the commoner class ({row['test_cells']} cells)")
    print(f"{'offset':>12s} {'NLOS median':>12s} {'NLOS RMSE':>10s} {'LOS median':>11s} {'LOS RMSE':>9s}"
          "  (|error|, samples)")
    for name, row in (("ml_frame", result["ml_frame"]), *((f"+ {k}", v) for k, v in corrections.items())):
        print(f"{name:>12s} {row['nlos_median_abs']:12.3f} {row['nlos_rmse']:10.3f} {row['los_median_abs']:11.3f} "
              f"{row['los_rmse']:9.3f}")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
