"""What tracking known cells by their full frame would add on a route: sites held per stack.

Replays a route bag through the pipeline (10-frame stacks, back to back; otherwise its defaults:
a tower database, the cells found tracked, ``ml_frame`` timing) and, on the very same stacks, tests every cell of
the database that is on the air and has a bandwidth there with its full-frame template (codes +
CRS, ``SyncTemplates.frame_template``) at its **true** position +-1 sample, the way a tracked
cell is tested (2 phases x 3 lags, the CFAR threshold for 1e-3 per stack over those 6 tests).
The true position stands in for the track: an oracle, so this is what full-frame tracking could
hold once a cell has been found, not what the pipeline does. No other cell is cancelled
first. Per stack: the sites the pipeline reports, and those the full frame holds; per site, the
full-frame timing error against the truth (the peak refined on a 1/16-sample grid, then a
parabola). False holds: the same test at four positions per cell where its code is not.

    python benchmarks/detection/full_frame_tracking.py [--route route_dense]

Needs the route bag (scripts/route_bags.sh). Writes docs/results/full_frame_tracking_ROUTE.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import scipy.fft
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from deepsync.frontend.templates import SyncTemplates
from deepsync.numeric import mad_spread
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import BagSource
from deepsync.sync.correlation import correlate, template_spectra
from deepsync.sync.search import cfar_threshold
from deepsync.sync.stacking import FrameStacker
from deepsync.towers import load_tower_database
from full_frame_template import COARSE, TRACK_LAGS, refine, unit_templates, wrapped

REPO = Path(__file__).resolve().parents[2]
# a fix every 10 frames, as docs/results/full_frame_tracking_*.json and docs/design/cell_search.md count
# sites per stack: the default 100-frame stack (a walker's) would hear more per stack and give
# ten times fewer stacks to count over
TEN_FRAMES = PipelineConfig().with_choices(n_frames=10)
ELSEWHERE = (2311, 5003, 7717, 12007)  # samples from the true position: where the cell is not


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--route", default="route_dense")
    parser.add_argument("--towers", help="tower database (default config/towers/ROUTE.yaml)")
    args = parser.parse_args()
    bag = REPO / "bags" / "generated" / args.route
    if not bag.exists():
        raise SystemExit(f"{bag} is missing: make it with scripts/route_bags.sh")
    towers_path = Path(args.towers) if args.towers else REPO / "config" / "towers" / f"{args.route}.yaml"
    source, towers, config = BagSource(bag), load_tower_database(towers_path), TEN_FRAMES
    pipeline = Pipeline(source.frontend, config, towers=towers)
    stacker = FrameStacker(source.frontend.adc_rate_hz, config.sync.stack)  # the pipeline's stacks, again
    templates = SyncTemplates(source.frontend)
    truth, bandwidths = source.truth_arrivals(), towers.bandwidths()
    site_of = {cell.pci: cell.site for cell in towers.cells}
    on_air = [pci for pci in truth if pci in bandwidths]
    frame = stacker.frame_samples
    spectra = {pci: template_spectra(unit_templates(templates, bandwidths[pci], pci)["full frame"], frame)
               for pci in on_air}
    threshold = cfar_threshold(1e-3, len(COARSE) * len(TRACK_LAGS))
    stacks, false_holds = [], []
    with threadpool_limits(1), tqdm(desc=args.route, unit=" stacks") as bar:
        for chunk in source.chunks():
            for result, stack in zip(pipeline.process(chunk), stacker.push(chunk)):
                spectrum = scipy.fft.rfft(stack.stacked() - stack.stacked().mean())
                held: dict[str, tuple[float, float]] = {}
                for pci in on_air:
                    arrivals = truth[pci]
                    after = arrivals[np.searchsorted(arrivals, stack.first_sample_index - 1):]
                    if not after.size or after[0] >= stack.first_sample_index + frame:
                        continue
                    position = after[0] - stack.first_sample_index
                    c = correlate(spectrum, spectra[pci], frame).astype(np.float64)
                    z = c / mad_spread(c[COARSE], centre=0.0)
                    for shift in ELSEWHERE:
                        false_holds.append(bool(z[COARSE][:, (round(position) + shift + TRACK_LAGS) % frame].max() > threshold))
                    lags = (round(position) + TRACK_LAGS) % frame
                    near = z[COARSE][:, lags]
                    if near.max() <= threshold:
                        continue
                    lag = int(lags[np.unravel_index(np.argmax(near), near.shape)[1]])
                    error = wrapped(refine(c, lag) - position, frame)
                    site = site_of[pci]
                    held[site] = max(held.get(site, (0.0, 0.0)), (float(near.max()), float(error)))
                reported = sorted({site_of[c.pci] for c in result.timing.cells if c.pci in site_of})
                stacks.append({"first_sample_index": stack.first_sample_index, "reported": reported, "held": held})
                bar.update()

    reported = np.array([len(s["reported"]) for s in stacks])
    either = np.array([len(set(s["reported"]) | set(s["held"])) for s in stacks])
    sites = {}
    for site in sorted({name for s in stacks for name in [*s["reported"], *s["held"]]}):
        errors = np.array([s["held"][site][1] for s in stacks if site in s["held"]])
        sites[site] = {
            "stacks_reported": sum(site in s["reported"] for s in stacks),
            "stacks_held_by_full_frame": int(errors.size),
            "median_z": float(np.median([s["held"][site][0] for s in stacks if site in s["held"]])) if errors.size else None,
            "median_error_samples": float(np.median(errors)) if errors.size else None,
            "rms_error_samples": float(np.sqrt(np.mean(errors**2))) if errors.size else None,
        }
    document = {
        "route": args.route, "towers": str(towers_path.relative_to(REPO)), "stacks": len(stacks),
        "frames_per_stack": config.sync.stack.n_frames,
        "sites_per_stack": {"reported": float(reported.mean()), "reported_or_held_by_full_frame": float(either.mean())},
        "stacks_with_3_sites": {"reported": float(np.mean(reported >= 3)),
                                "reported_or_held_by_full_frame": float(np.mean(either >= 3))},
        "false_holds": {"tests": len(false_holds), "rate": float(np.mean(false_holds)), "design_rate": 1e-3},
        "sites": sites,
    }
    print(f"{args.route}, {len(stacks)} stacks of {config.sync.stack.n_frames} frames:")
    print(f"  sites per stack: reported {reported.mean():.2f}; reported or held by the full frame {either.mean():.2f}")
    print(f"  stacks with >= 3 sites: {100 * np.mean(reported >= 3):.0f} % -> {100 * np.mean(either >= 3):.0f} %")
    print(f"  false holds where a cell is not: {sum(false_holds)} of {len(false_holds)} tests "
          f"({100 * np.mean(false_holds):.2f} %, design 0.1 %)")
    print("  site   stacks reported   held by full frame (median z)   full-frame timing error: median / RMS (samples)")
    for site, row in sites.items():
        held = "-" if row["median_z"] is None else (f"{row['stacks_held_by_full_frame']:4d} ({row['median_z']:.1f})       "
                                                    f"      {row['median_error_samples']:+.3f} / {row['rms_error_samples']:.3f}")
        print(f"  {site:5s}  {row['stacks_reported']:6d}            {held}")
    out = REPO / "docs" / "results" / f"full_frame_tracking_{args.route}.json"
    out.write_text(json.dumps(document, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
