"""The live simulator as a source: a scenario's envelope stream, computed as it is read.

What ``deepsync simulate`` records into a bag, without the bag: the same twin, front end, seed
and receiver clock epoch, so the first seconds of this stream equal the recorded bag's samples.
Useful to run the nodes on a scenario nobody has recorded. The simulator computes the real
physics (every resource element of every cell, the square law, the channel): about 0.9x real
time on one core for the campus scenario on this project's machines, less for more cells
(docs/design/simulator.md). A paced consumer falls behind, and says so (the ``envelope_adc`` node's
diagnostics); ``workers`` spreads the stream over processes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator

from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.recording import EPOCH_NS
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario
from deepsync.types import FRAME_SECONDS, EnvelopeChunk

SCENARIO_SUFFIXES = (".yaml", ".yml")
DEFAULT_SECONDS = 3600.0  # an hour of signal: "live" for any session, yet a finite stream


def is_scenario_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a scenario file (by its suffix)."""
    return os.fspath(path).lower().endswith(SCENARIO_SUFFIXES)


class SimulatorSource:
    """``seconds`` of the scenario at ``path``, simulated chunk by chunk as they are read."""

    def __init__(self, path: str | os.PathLike, seconds: float = DEFAULT_SECONDS, seed: int | None = None,
                 workers: int = 1) -> None:
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds >= FRAME_SECONDS):
            raise ValueError(f"{os.fspath(path)}: simulate at least one 10 ms frame, got seconds={seconds!r}")
        self.path = os.fspath(path)
        self.scenario = load_scenario(self.path)
        self.seed = self.scenario.seed if seed is None else int(seed)
        self.seconds = float(seconds)
        self.workers = int(workers)
        self.twin = build_twin(self.scenario)
        self.frontend = self.twin.frontend
        self.center_hz: float | None = None  # an envelope detector sees every carrier in its RF band

    @property
    def description(self) -> str:
        return (f"live simulation of scenario {self.scenario.name!r} ({self.path}, seed {self.seed}): "
                f"{len(self.twin.emitters)} cells at {self.frontend.adc_rate_hz / 1e6:g} MS/s")

    def chunks(self) -> Iterator[EnvelopeChunk]:
        """The stream from sample 0, one LTE frame per chunk (a fresh simulator each call)."""
        simulator = EnvelopeSimulator(self.twin.emitters, self.twin.channel, self.frontend, self.seed,
                                      epoch_ns=EPOCH_NS)
        chunk = max(1, round(FRAME_SECONDS * self.frontend.adc_rate_hz))
        return simulator.stream(self.seconds, chunk_samples=chunk, workers=self.workers)
