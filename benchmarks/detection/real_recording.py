"""The pipeline on the real RTL-SDR recording against the coherent (complex-domain) reference search.

For the recording as it is and scaled up 16x around mid-scale (clipped to 8 bits, as an RTL-SDR
with more gain would have written it), both read as a source with the default envelope scale
(the recording's peak -> code 32766): which cells are named, in how many stacks, and how far
the search's code positions and the timing stage's arrivals lie from the coherent timing
(median over stacks and spread across them, samples; 1 sample = 156 m). The database gives no
bandwidth, so the cells are timed on their code windows (ML); the recording is also run with
the database claiming 1.4 and 10 MHz for every cell, so that each cell's whole known frame is
fitted (``ml_frame``), as far as the recording's 1.92 MHz passband shows it. Needs ``../shared/data/real_lte``.

    .venv/bin/python benchmarks/detection/real_recording.py   # -> docs/results/real_recording.json
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from deepsync.testing.coherent import search_cells
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import RawFileSource, read_iq
from deepsync.towers import load_tower_database

REPO = Path(__file__).resolve().parents[2]
RECORDING = REPO.parent / "shared" / "data" / "real_lte" / "f1860_s1.92_g0_1s_strong_rtlsdr.bin"
TOWERS = REPO / "config" / "towers" / "real_lte_1860.yaml"
OUT = REPO / "docs" / "results" / "real_recording.json"
# the recording's carrier is not known; through its 1.92 MHz passband every carrier of 3 MHz or
# more gives the same CRS template (10 MHz stands for them), 1.4 MHz only the middle 72 subcarriers
BANDWIDTHS_MHZ = (1.4, 10.0)
# the recording is one second: 10-frame stacks give nine stacks to compare, where the default
# 100-frame stack (a walker's) would give one
TEN_FRAMES = PipelineConfig().with_choices(n_frames=10)


def offset(reference, position: float) -> float:
    """Samples from the nearest coherent code of the cell to ``position``."""
    frames = round((position - reference.sync_position) / reference.samples_per_frame)
    return position - (reference.sync_position + frames * reference.samples_per_frame)


def evaluate(path: Path, references: dict, towers: Path = TOWERS) -> dict:
    source = RawFileSource(path, "cu8", 1.92e6)
    results = list(Pipeline(source.frontend, TEN_FRAMES, towers=load_tower_database(towers)).run(source.chunks()))
    cells: dict[int, dict[str, list]] = {}
    for result in results:
        for cell in result.sync.cells:
            cells.setdefault(cell.pci, {"search": [], "ml": [], "estimator": []})["search"].append(
                offset(references[cell.pci], cell.code_position))
        for timing in result.timing.cells:
            cells[timing.pci]["ml"].append(offset(references[timing.pci], timing.toa))
            cells[timing.pci]["estimator"].append(timing.estimator)
    return {
        "scale": source.scale,
        "stacks": len(results),
        "clock_ppm": [round(r.sync.clock_drift_ppm, 2) for r in results if r.sync.clock_drift_ppm is not None],
        "cells": {pci: {"stacks_reported": len(v["ml"]),
                        "median_search_offset": round(statistics.median(v["search"]), 3),
                        "estimator": sorted(set(v["estimator"])),
                        "median_ml_offset": round(statistics.median(v["ml"]), 3),
                        "ml_offset_spread": round(statistics.pstdev(v["ml"]), 3)}
                  for pci, v in sorted(cells.items())},
    }


def with_bandwidth(directory: Path, bandwidth_mhz: float) -> Path:
    """The recording's tower database with every cell at ``bandwidth_mhz`` (the recording does
    not say its carrier's): what lets the timing stage fit the cells' whole frames."""
    path = directory / f"towers_{bandwidth_mhz:g}mhz.yaml"
    path.write_text(TOWERS.read_text().replace("earfcn: 1750}", f"earfcn: 1750, bandwidth_mhz: {bandwidth_mhz:g}}}"))
    return path


def main() -> int:
    if not RECORDING.exists():
        print(f"the real recording is not at {RECORDING}", file=sys.stderr)
        return 1
    references = {cell.pci: cell for cell in search_cells(read_iq(RECORDING, "cu8"))}
    with tempfile.TemporaryDirectory() as tmp:
        loud = Path(tmp) / "loud.cu8"
        raw = np.fromfile(RECORDING, dtype=np.uint8).astype(np.float64)
        np.clip(np.round(127.5 + 16 * (raw - 127.5)), 0, 255).astype(np.uint8).tofile(loud)
        report = {
            "coherent_clock_ppm": round(references[142].clock_ppm, 2),
            "original": evaluate(RECORDING, references),
            "scaled_16x": evaluate(loud, references),
            **{f"original, database bandwidth {bandwidth:g} MHz": evaluate(
                RECORDING, references, with_bandwidth(Path(tmp), bandwidth)) for bandwidth in BANDWIDTHS_MHZ},
        }
    for name in [key for key in report if key != "coherent_clock_ppm"]:
        print(f"{name}: scale {report[name]['scale']:.4g} per code, clock {min(report[name]['clock_ppm'])}.."
              f"{max(report[name]['clock_ppm'])} ppm (coherent {report['coherent_clock_ppm']})")
        for pci, cell in report[name]["cells"].items():
            print(f"  PCI {pci:3d}: {cell['stacks_reported']} of {report[name]['stacks']} stacks, search "
                  f"{cell['median_search_offset']:+.3f}, {'/'.join(cell['estimator'])} {cell['median_ml_offset']:+.3f} "
                  f"(spread {cell['ml_offset_spread']:.3f}) samples from the coherent timing")
    OUT.write_text(json.dumps(report, indent=1))
    print(f"-> {OUT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
