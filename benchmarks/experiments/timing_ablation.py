"""The paper's fusion ablation, and the soft-argmax head, at one training budget.

Each variant is the shipped network's config (``config/timing/timing_net.yaml``: the same data,
encoders, dense layers, loss, batch and seed) with another ``model.fusion`` or ``model.head``,
trained for the same number of steps (the cosine schedule compressed to them), then scored on
the fixed test split with 10 frames against the true first path: median, p90 and RMSE of the
error, the share of outliers (beyond a sample), the median per SNR bin, the sigma calibration,
parameters and FLOPs. ML on the same windows is the yardstick. The budget is a CPU one (the
shipped network had 5x more steps): it ranks the variants, it does not say where each ends.

A variant is ``fusion[+head][@poolN]``: ``@pool1`` gives the encoders one token per sample
instead of the shipped two (a lag grid twice as fine for the votes, at twice the FLOPs).
``--test-data`` scores another test split (the clean channel's, ``benchmarks/timing/split_variants.py clean``)
and ``--name`` keeps its results apart from the ablation's.

Run:  .venv/bin/python benchmarks/experiments/timing_ablation.py  [--steps 2000] [--jobs 2] [--variants ...]
                                                      [--test-data DIR] [--name ablation]
Interrupt at any time: a rerun resumes each variant's training (``runs/ablation/<variant>``)
and skips what is scored. Writes docs/results/timing_network/<name>.json and <name>.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepsync.eval.timing import SNR_EDGES_DB, error_stats
from deepsync.timing.estimators import estimate_ml, noise_psd
from deepsync.timing.model import count_flops
from deepsync.timing.network import NetworkEstimator
from deepsync.training.dataset import LOS_PROFILES, PROFILES, load_split
from deepsync.training.train import RunConfig, load_run_config, train

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "results" / "timing_network"
VARIANTS = ("cross_attention", "concatenation", "addition", "correlation",
            "cross_attention+soft_argmax", "correlation+soft_argmax")
FRAMES = 10


def variant_run(base: RunConfig, variant: str, steps: int) -> RunConfig:
    """``base`` with the variant's fusion (and head, after a '+'; pool, after '@pool'), trained
    ``steps`` steps on one thread."""
    layout, _, pool = variant.partition("@pool")
    fusion, _, head = layout.partition("+")
    run_dir = ROOT / "runs" / "ablation" / variant
    model = dataclasses.replace(base.model, fusion=fusion, head=head or "dense",
                                pool=int(pool) if pool else base.model.pool)
    training = dataclasses.replace(base.training, steps=steps, run_dir=str(run_dir), threads=1,
                                   model_path=str(run_dir / "best.pt"), data_dir=str(ROOT / base.training.data_dir))
    return dataclasses.replace(base, model=model, training=training)


def train_variant(run: RunConfig) -> str:
    return str(train(run))


def score(errors: np.ndarray, sigmas: np.ndarray, data: dict[str, np.ndarray]) -> dict:
    los = np.isin(data["profile"], [PROFILES.index(p) for p in LOS_PROFILES])
    out = {"all": error_stats(errors, sigmas), "median_by_snr": []}
    for low, high in zip(SNR_EDGES_DB[:-1], SNR_EDGES_DB[1:]):
        inside = (data["snr_db"] >= low) & (data["snr_db"] < high)
        out["median_by_snr"].append({"snr_db": [float(low), float(high)], **error_stats(errors[inside], sigmas[inside])})
    out["los_from_0_db"] = error_stats(errors[los & (data["snr_db"] >= 0)], sigmas[los & (data["snr_db"] >= 0)])
    middle = (data["snr_db"] >= -10) & (data["snr_db"] < 0)
    out["all_channels_-10_to_0_db"] = error_stats(errors[middle], sigmas[middle])
    return out


def network_errors(path: Path, data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, dict]:
    network = NetworkEstimator(path, threads=2)
    windows, templates = data["windows"][:, :FRAMES], data["template"]
    estimates = [e for start in range(0, len(windows), 256)
                 for e in network.estimate(list(windows[start : start + 256]), list(templates[start : start + 256]))]
    offsets, sigmas = np.array(estimates).T
    model = network.model
    cost = {"parameters": sum(p.numel() for p in model.parameters()), "mflops": count_flops(model, FRAMES) / 1e6}
    return offsets - data["offset"], sigmas, cost


def ml_errors(data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    windows, templates = data["windows"][:, :FRAMES], data["template"]
    margin = (windows.shape[2] - templates.shape[1]) // 2
    errors, sigmas = np.empty(len(windows)), np.empty(len(windows))
    for i in tqdm(range(len(windows)), desc="ML on the test split"):
        w = windows[i].astype(np.float64)
        result = estimate_ml(w, templates[i].astype(np.float64), margin, noise_psd(w))
        errors[i], sigmas[i] = result.offset - data["offset"][i], result.std
    return errors, sigmas


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(13, 4.5))
    for name in summary["variants"]:
        history = json.loads((ROOT / "runs" / "ablation" / name / "history.json").read_text())
        left.plot([h["step"] for h in history], [h["val_median_abs_error"] for h in history], marker=".", label=name)
    left.set_title(f"validation median |error|, {FRAMES} frames")
    left.set_xlabel("step")
    left.set_ylabel("samples")
    left.set_yscale("log")
    for name, result in {**summary["variants"], "ml": summary["ml"]}.items():
        rows = result["median_by_snr"]
        right.semilogy([np.mean(r["snr_db"]) for r in rows], [r.get("median", np.nan) for r in rows], marker="o",
                       label=name, linestyle="--" if name == "ml" else "-")
    right.set_title(f"test split, {FRAMES} frames: median |error| vs true first path")
    right.set_xlabel("per-frame SNR (dB)")
    right.set_ylabel("samples")
    for ax in (left, right):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=str(ROOT / "config" / "timing" / "timing_net.yaml"))
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--jobs", type=int, default=2, help="variants trained at once (one thread each)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--test-data", help="the data directory (in the repository) whose test split is scored "
                        "(default: the training data's)")
    parser.add_argument("--name", default="ablation", help="stem of the JSON and PNG written")
    args = parser.parse_args()
    base = load_run_config(args.config)
    runs = {name: variant_run(base, name, args.steps) for name in args.variants}
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(train_variant, runs.values()))

    test_data = args.test_data or base.training.data_dir
    data = load_split(ROOT / test_data, "test")
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{args.name}.json"
    summary = json.loads(path.read_text()) if path.exists() else {}
    if (summary.get("steps"), summary.get("test_data")) != (args.steps, test_data):  # ML's row is of that split
        summary = {"steps": args.steps, "frames": FRAMES, "test_data": test_data,
                   "examples": int(len(data["offset"])), "variants": {}}
    if "ml" not in summary:
        summary["ml"] = score(*ml_errors(data), data)
    for name, run in runs.items():
        errors, sigmas, cost = network_errors(Path(run.training.model_path), data)
        summary["variants"][name] = {**cost, **score(errors, sigmas, data)}
        row = summary["variants"][name]["all"]
        print(f"{name:28s} median {row['median']:.3f}  p90 {row['p90']:.2f}  RMSE {row['rmse']:.2f}  "
              f"outliers {row['outliers']:.1%}  params {cost['parameters']}  {cost['mflops']:.1f} MFLOP")
    ml = summary["ml"]["all"]
    print(f"{'ml':28s} median {ml['median']:.3f}  p90 {ml['p90']:.2f}  RMSE {ml['rmse']:.2f}  outliers {ml['outliers']:.1%}")
    path.write_text(json.dumps(summary, indent=1))
    plot(summary, OUT / f"{args.name}.png")
    print(f"wrote {path} and {OUT / f'{args.name}.png'}")


if __name__ == "__main__":
    main()
