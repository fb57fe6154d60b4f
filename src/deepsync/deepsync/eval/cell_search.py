"""Cell search and timing against ground truth: one record per stack, one summary per cell
(``CellSearch``: what ``deepsync detect`` runs and prints).

The truth of a simulated recording gives each cell's sync-code arrivals in stream samples, one
per frame; an estimate is compared with the nearest true arrival in time (the arrivals move
with a walking receiver and drifting site clocks; one sample at 1.92 MHz is 156 m of range).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from deepsync.pipeline import Pipeline, PipelineConfig, StackResult
from deepsync.sources import BagSource, LiveSource, Source
from deepsync.sync.search import Candidate
from deepsync.towers import TowerDatabase
from deepsync.types import FRAME_SECONDS, Health


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


@dataclass(frozen=True)
class SearchedStack:
    """A stack the search went through: the pipeline's result and its ``stack_record``."""

    result: StackResult
    record: dict

    @property
    def quiet(self) -> bool:
        """Nothing found in it, not even tentatively, and no event before it."""
        return not (self.record["cells"] or self.record["events"] or self.result.sync.tentative)


class CellSearch:
    """The pipeline (cell search and timing; no fusion) over a source, each stack scored against
    the truth a bag holds: ``run`` yields the stacks as they come, and a live source's events
    between them; ``summary`` is per cell, over the stacks run so far."""

    def __init__(self, source: Source, towers: TowerDatabase | None, n_frames: int) -> None:
        self.source = source
        self.towers = towers
        self.config = PipelineConfig().with_choices(n_frames)
        self.truth: dict[int, np.ndarray] = source.truth_arrivals() if isinstance(source, BagSource) else {}
        self.stacks: list[dict] = []

    def run(self) -> Iterator[SearchedStack | Health]:
        """Every stack, and a live source's events as they arrive. Raises ValueError, once the
        source is done, when it gave no stack at all, saying why."""
        pipeline = Pipeline(self.source.frontend, self.config, self.towers)
        live = self.source if isinstance(self.source, LiveSource) else None
        samples = 0
        for chunk in self.source.chunks():
            samples += len(chunk.samples)
            yield from live.take_events() if live else ()
            for result in pipeline.process(chunk):
                self.stacks.append(stack_record(result, self.truth, self.source.frontend.adc_rate_hz))
                yield SearchedStack(result, self.stacks[-1])
        yield from live.take_events() if live else ()
        if not self.stacks:
            frames = self.config.sync.stack.n_frames
            frame = round(self.source.frontend.adc_rate_hz * FRAME_SECONDS)
            reason = (f"it holds {samples} samples ({samples / frame:.1f} frames), less than one {frames}-frame stack"
                      if samples < frames * frame else "no stretch of it was clean for a whole stack (see the events)")
            raise ValueError(f"no stack to search in {self.source.description}: {reason}")

    def summary(self) -> dict:
        """``summarize`` of the stacks run."""
        return summarize(self.stacks, self.truth)
