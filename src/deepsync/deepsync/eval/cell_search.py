"""Cell search and timing against ground truth: one record per stack, one summary per cell.

The truth of a simulated recording gives each cell's sync-code arrivals in stream samples, one
per frame; an estimate is compared with the nearest true arrival in time (the arrivals move
with a walking receiver and drifting site clocks; one sample at 1.92 MHz is 156 m of range).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence

import numpy as np

from deepsync.pipeline import StackResult
from deepsync.sync.search import Candidate


def timing_error(toa: float, truth: np.ndarray) -> float:
    """Estimate minus the nearest true arrival (samples); NaN without one."""
    if truth.size == 0:
        return math.nan
    i = int(np.searchsorted(truth, toa))
    neighbours = truth[max(i - 1, 0) : i + 1]  # the true arrivals either side
    return float(toa - neighbours[np.argmin(np.abs(neighbours - toa))])


RUNNERS_UP = 3  # the other PCIs a reported cell lists


def runners_up(pci: int, candidates: Sequence[Candidate]) -> list[int]:
    """The PCIs ranked next for a reported cell: the best ``RUNNERS_UP`` of ``candidates`` other
    than the cell itself (which the tower database may have chosen from below the top)."""
    return [c.pci for c in candidates if c.pci != pci][:RUNNERS_UP]


def stack_record(result: StackResult, truth: Mapping[int, np.ndarray], sample_rate: float) -> dict:
    """A stack's confirmed cells with their arrivals (and errors against ``truth``, PCI -> its true
    arrivals, where it has the PCI), its flags and the stream events before it, as plain data."""
    timings = {timing.pci: timing for timing in result.timing.cells}
    cells = []
    for cell in result.sync.cells:
        timing = timings.get(cell.pci)
        if timing is None:
            continue  # could not be timed: an event of the stack says why
        detection = cell.detection
        cells.append({
            "pci": cell.pci,
            "toa": timing.toa,
            "std": timing.toa_std,
            "crlb_std": timing.crlb_std,
            "estimator": timing.estimator,
            "snr_db": timing.snr_db,
            "peak_sigma": detection.peak_metric,
            "truth_error": timing_error(timing.toa, truth[cell.pci]) if cell.pci in truth else None,
            "runners_up": runners_up(cell.pci, detection.candidates),
        })
    return {
        "time_s": result.sync.first_sample_index / sample_rate,
        "clock_drift_ppm": result.sync.clock_drift_ppm,
        "flags": [str(flag) for flag in result.sync.flags],
        "events": [str(event) for event in result.sync.events + result.timing.events],
        "cells": cells,
    }


def summarize(stacks: list[dict], truth: Mapping[int, np.ndarray]) -> dict:
    """Per cell: in how many stacks it was reported, its median SNR and claimed std, its RMS
    error against the truth; and the truth cells never reported. ``in_truth`` is None where
    there is no truth to compare with."""
    by_pci: dict[int, list[dict]] = {}
    for stack in stacks:
        for cell in stack["cells"]:
            by_pci.setdefault(cell["pci"], []).append(cell)
    cells = {}
    for pci, found in sorted(by_pci.items()):
        errors = [c["truth_error"] for c in found if c["truth_error"] is not None]
        cells[pci] = {
            "stacks_reported": len(found),
            "in_truth": (pci in truth) if truth else None,
            "median_snr_db": statistics.median(c["snr_db"] for c in found),
            "median_claimed_std": statistics.median(c["std"] for c in found),
            "rms_truth_error": math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None,
        }
    return {"stacks": len(stacks), "cells": cells, "missed": sorted(set(truth) - set(by_pci))}
