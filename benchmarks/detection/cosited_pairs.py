"""Co-sited sector pairs: detection with and without the site hypothesis, 10-frame stacks.

Interference as in cell_search.py (the envelope of a simulated, fully loaded 10 MHz cell).
Each trial adds the coinciding codes of two sectors of one site, |x s_a + y s_b|^2 through
the chain (``SiteFit.template``), at a random sub-sample position and a random relative phase
arg(x y*), with the partner's amplitude ratio y/x of 1 (equal power), 0.5 (-6 dB) or 0 (a
lone sector). The SNR is sector a's own per-frame sync SNR, as in cell_search.py. The tower
database: seven three-sector sites (21 PCIs), the trial's site, the resident cell's and five
others. Searched with the site hypothesis (``cosited_pairs`` given) and with single
templates only.

* both: both sectors reported within 1 sample of the code.
* pair: both reported as one pair (carrying the pair's fit).
* any: at least one of them reported there.
* wrong partner (lone sector): another PCI of the site reported at the code.
* Pfa: stacks of interference alone with any detection besides the resident cell.

Run:  .venv/bin/python benchmarks/detection/cosited_pairs.py [--trials 200]
Writes docs/results/cosited_pairs.json and docs/results/cosited_pairs.png.
"""

from __future__ import annotations

import argparse
import json
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from cell_search import FRAME, HALF, OUT, RESIDENT_PCI, interference, near  # noqa: E402
from tqdm import tqdm  # noqa: E402

from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.templates import SyncTemplates  # noqa: E402
from deepsync.sync.search import CellSearch  # noqa: E402
from deepsync.sync.sites import SiteFit  # noqa: E402
from deepsync.towers import parse_tower_database  # noqa: E402

SNR_GRID = np.arange(-30.0, -11.9, 2.0)
RATIOS = {"equal": 1.0, "-6 dB": 0.5, "lone": 0.0}
FRAMES = 10


def site_database(groups: list[int]):
    """A tower database of three-sector sites, one per PCI group (N_ID1)."""
    sites = [{"name": f"g{g}", "cells": [{"pci": 3 * g + k, "earfcn": 2000} for k in range(3)]} for g in groups]
    return parse_tower_database({"name": "benchmark", "sites": sites})


def pair_codes(templates, pcis, ratio, phase, offset):
    """One frame of the pair's two coinciding codes (zero-mean), in sector a's template units."""
    mixed = ratio * np.exp(1j * phase)
    fit = SiteFit(pcis, (1.0, ratio**2, mixed.real, -mixed.imag))
    codes = np.zeros(FRAME)
    for subframe, at in ((0, offset), (5, offset + HALF)):
        whole = int(np.floor(at))
        shape = fit.template(templates, subframe, at - whole)
        codes[(whole + np.arange(len(shape))) % FRAME] += shape - shape.mean()
    return codes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=4.0, help="interference to simulate")
    args = parser.parse_args()
    rng = np.random.default_rng(2027)
    templates = SyncTemplates(FrontendConfig())
    print(f"simulating {args.seconds:g} s of interference ...")
    frames, resident = interference(args.seconds, templates.config)
    sigma = float(np.std(frames[:, (np.arange(FRAME) - resident) % HALF > 400]))

    resident_group = RESIDENT_PCI // 3
    choices = np.setdiff1d(np.arange(168), [resident_group])
    searches = []  # (site group, with site hypothesis, single templates only)
    for group in rng.choice(choices, 8, replace=False):
        others = rng.choice(np.setdiff1d(choices, [group]), 5, replace=False)
        db = site_database([int(group), resident_group, *others.tolist()])
        searches.append((int(group), CellSearch(templates, None, db.pcis, db.cosited_pairs()),
                         CellSearch(templates, None, db.pcis)))

    def trial(snr_db: float | None, ratio: float) -> dict[str, tuple[bool, ...]]:
        group, with_sites, singles = searches[rng.integers(len(searches))]
        a, b = sorted(3 * group + rng.choice(3, 2, replace=False))
        start = rng.integers(0, len(frames) - FRAMES)
        stacked = frames[start : start + FRAMES].mean(axis=0)
        offset = rng.uniform(0, FRAME)
        if snr_db is not None:
            own = templates.template(int(a), 0, offset % 1)
            energy = np.sum((own - own.mean()) ** 2)
            power = math.sqrt(10 ** (snr_db / 10) * len(own) * sigma**2 / energy)
            stacked = stacked + power * pair_codes(templates, (int(a), int(b)), ratio, rng.uniform(0, 2 * np.pi), offset)
        outcome = {}
        for mode, search in (("site", with_sites), ("single", singles)):
            found = search.search(stacked)
            here = [d for d in found if snr_db is not None and near(d.frame_offset + d.fraction, offset, FRAME)]
            named = {d.pci for d in here}
            false = [d for d in found if d not in here and not near(d.frame_offset + d.fraction, resident, HALF)]
            outcome[mode] = (
                {a, b} <= named,
                {a, b} <= {d.pci for d in here if d.site is not None and d.site.pcis == (a, b)},
                bool(named & {a, b}),
                bool(named - {a}) if ratio == 0 else False,
                bool(false),
            )
        return outcome

    keys = ("both", "pair", "any", "wrong_partner", "false_elsewhere")
    results: dict = {"definition": __doc__.split("\n\n")[1], "trials": args.trials, "frames": FRAMES, "curves": {}}
    with tqdm(total=(len(RATIOS) * len(SNR_GRID) + 1) * args.trials, desc="co-sited pairs") as bar:
        for name, ratio in RATIOS.items():
            points = []
            for snr in SNR_GRID:
                tally = {m: np.zeros(len(keys)) for m in ("site", "single")}
                for _ in range(args.trials):
                    for mode, values in trial(float(snr), ratio).items():
                        tally[mode] += values
                    bar.update()
                points.append({"snr_db": float(snr), **{m: dict(zip(keys, t / args.trials)) for m, t in tally.items()}})
            results["curves"][name] = points
        false = np.zeros(2)
        for _ in range(args.trials):
            outcome = trial(None, 0.0)
            false += [outcome["site"][4], outcome["single"][4]]
            bar.update()
        results["pfa"] = {"site": false[0] / args.trials, "single": false[1] / args.trials}

    print(f"\n{FRAMES}-frame stacks, {args.trials} trials per point; SNR = sector a's own per-frame sync SNR")
    for name, points in results["curves"].items():
        print(f"  partner {name}:")
        for p in points:
            s, n = p["site"], p["single"]
            extra = f"  wrong partner {s['wrong_partner']:.2f}" if name == "lone" else ""
            print(f"    {p['snr_db']:6.1f} dB  site hypothesis: both {s['both']:.2f} as a pair {s['pair']:.2f} "
                  f"any {s['any']:.2f}{extra}  | single templates: both {n['both']:.2f} any {n['any']:.2f}")
        for mode in ("site", "single"):
            needed = next((p["snr_db"] for p in points if p[mode]["both" if name != "lone" else "any"] >= 0.99), math.nan)
            results[f"snr_for_pd99_{name}_{mode}"] = needed
    print(f"  false-alarm rate per stack (interference alone): site hypothesis {results['pfa']['site']:.3f}, "
          f"single templates {results['pfa']['single']:.3f}")

    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "cosited_pairs.json").write_text(json.dumps(results, indent=2))
    fig, axes = plt.subplots(1, len(RATIOS), figsize=(15, 4), sharey=True)
    for ax, (name, points) in zip(axes, results["curves"].items()):
        snrs = [p["snr_db"] for p in points]
        metric = "any" if name == "lone" else "both"
        for mode, style in (("site", "-o"), ("single", "--s")):
            ax.plot(snrs, [p[mode][metric] for p in points], style, ms=3, label=f"{mode}: {metric}")
        if name == "lone":
            ax.plot(snrs, [p["site"]["wrong_partner"] for p in points], ":", label="site: wrong partner")
        ax.set_title(f"partner {name}", fontsize=10)
        ax.set_xlabel("sector a's per-frame sync SNR (dB)")
        ax.axhline(0.99, color="grey", lw=0.5)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("probability")
    fig.tight_layout()
    fig.savefig(OUT / "cosited_pairs.png", dpi=120)
    print(f"wrote {OUT / 'cosited_pairs.json'} and {OUT / 'cosited_pairs.png'}")


if __name__ == "__main__":
    main()
