"""How much weaker than a strong cell a second cell can be and still be found, with a tower database.

The envelope detector squares everything it hears: a strong cell's data raises the noise for
every other cell, and its CRS, which stacking does not average away, passes for weaker cells'
codes over long stacks. Here a strong cell (PCI 456, 10 MHz, load 0.6, -85 dBm per RE, line of
sight) and a second cell on the same carrier (PCI 301, 2.4 ms later in the frame) at a lower
power go through the simulator and the default front end; 50-frame stacks are searched with a
20-PCI tower database holding both, with the strong cell's CRS cancelled (the default,
``crs_cancel_z`` 10) and without (0). Per power of the second cell: Pd (PCI 301 found within 1
sample of its code) and the share of stacks with a false cell (any other PCI).

Run:  .venv/bin/python benchmarks/detection/second_cell.py [--stacks 12]
Writes docs/results/second_cell.json.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from cell_search import near
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds
from deepsync.lte.cell import CellConfig
from deepsync.sync.search import CellSearch, SearchConfig
from deepsync.types import FRAME_SECONDS
from sync_snr import EIRP_PER_RE_W

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
STRONG, WEAK = 456, 301
STRONG_DBM = -85.0
DELAYS_S = (1.0e-6, 2.4e-3)  # the second cell's frame 2.4 ms after the strong one's: codes apart
FRAMES = 50
WEAK_DBM = np.arange(-85.0, -101.0, -2.0)


def stacks(weak_dbm: float, count: int, config: FrontendConfig) -> tuple[np.ndarray, float]:
    """(count, frame) 50-frame stacks of the two cells, and where the second cell's code sits."""
    gains = [math.sqrt(10 ** ((p - 30) / 10) / EIRP_PER_RE_W) for p in (STRONG_DBM, weak_dbm)]
    cells = [Emitter(CellConfig(pci=pci, bandwidth_mhz=10, load=0.6), 2115e6, EIRP_PER_RE_W, 0.0, 0.0, name)
             for pci, name in ((STRONG, "S"), (WEAK, "W"))]
    channel = FixedChannel([Paths([DELAYS_S[0]], [gains[0]], [0.0]), Paths([DELAYS_S[1]], [gains[1]], [0.0])])
    sim = EnvelopeSimulator(cells, channel, config, seed=int(-weak_dbm))
    frame = round(config.adc_rate_hz * FRAME_SECONDS)
    volts = np.concatenate([c.samples for c in sim.stream(count * FRAMES * FRAME_SECONDS, workers=2)])
    frames = volts[: count * FRAMES * frame].astype(np.float64).reshape(count, FRAMES, frame)
    code = float(sim.sample_index(sync_code_offset_seconds() + DELAYS_S[1])) % frame
    return frames.mean(axis=1), code


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stacks", type=int, default=12, help="50-frame stacks per power")
    args = parser.parse_args()
    config = FrontendConfig()
    templates = SyncTemplates(config)
    rng = np.random.default_rng(8)
    database = [STRONG, WEAK, *rng.choice(np.setdiff1d(np.arange(504), [STRONG, WEAK]), 18, replace=False).tolist()]
    searches = {z: CellSearch(templates, SearchConfig(crs_cancel_z=z), database) for z in (0.0, 10.0)}
    rows = []
    with threadpool_limits(1):
        for weak_dbm in tqdm(WEAK_DBM, desc="second cell"):
            stacked, code = stacks(float(weak_dbm), args.stacks, config)
            row = {"weak_dbm_per_re": float(weak_dbm)}
            for z, search in searches.items():
                found = [search.search(s) for s in stacked]
                hits = [any(d.pci == WEAK and near(d.frame_offset + d.fraction, code, len(s)) for d in cells)
                        for cells, s in zip(found, stacked)]
                false = [any(d.pci not in (STRONG, WEAK) for d in cells) for cells in found]
                row["crs_cancelled" if z else "crs_kept"] = {"pd": float(np.mean(hits)), "false_stacks": float(np.mean(false))}
            rows.append(row)
            print(f"  second cell {weak_dbm:6.1f} dBm/RE ({weak_dbm - STRONG_DBM:+.0f} dB): "
                  + ", ".join(f"{k}: Pd {v['pd']:.2f}, false {v['false_stacks']:.2f}" for k, v in row.items() if k != "weak_dbm_per_re"))
    weakest = {}
    for key in ("crs_kept", "crs_cancelled"):
        found = [r["weak_dbm_per_re"] for r in rows if r[key]["pd"] >= 0.9]
        weakest[key] = min(found) if found else None
    print(f"weakest second cell at Pd >= 90 % next to a {STRONG_DBM:g} dBm/RE cell, {FRAMES}-frame stacks: "
          f"{weakest['crs_kept']} dBm/RE with the strong cell's CRS kept, {weakest['crs_cancelled']} with it cancelled")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "second_cell.json").write_text(json.dumps({
        "description": __doc__.split("\n\n")[1], "strong_dbm_per_re": STRONG_DBM, "frames": FRAMES,
        "stacks_per_point": args.stacks, "rows": rows, "weakest_at_pd90_dbm_per_re": weakest}, indent=2))
    print(f"wrote {OUT / 'second_cell.json'}")


if __name__ == "__main__":
    main()
