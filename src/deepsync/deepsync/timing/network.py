"""The timing network as an estimator: many cells' windows in, offsets and sigmas out, one
batched forward pass per stack.

The checkpoint says what the network was trained on (``TrainingRange``); :meth:`NetworkEstimator.refusal`
names why a cell lies outside it, and the timing stage then times that cell with ML instead:

* another sample rate or window layout than the checkpoint's (its templates would not match);
* a co-sited pair found together (its code is a fitted mix of two sectors' codes), unless the
  checkpoint was trained on such pairs;
* fewer or more stacked frames than it was trained with;
* a per-frame SNR above the training range (the sync stage's stacked SNR less 10 log10 of the
  frames; at high SNR ML sits on the Cramer-Rao bound anyway). Below the range the network
  still answers: it was trained down to pure noise, and its sigma says how little it knows.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from deepsync.timing.checkpoint import TimingCheckpoint, load_checkpoint
from deepsync.timing.inputs import network_inputs
from deepsync.types import SyncWindow

DEFAULT_CHECKPOINT = Path(__file__).with_name("timing_net.pt")


class NetworkEstimator:
    """A checkpoint loaded once (``weights_only``), run on the CPU with ``threads`` threads."""

    def __init__(self, checkpoint: str | Path | None = None, threads: int = 1) -> None:
        self.path = Path(checkpoint) if checkpoint else DEFAULT_CHECKPOINT
        loaded: TimingCheckpoint = load_checkpoint(self.path)
        self.model = loaded.model.eval()
        self.range = loaded.training_range
        self.normalisation = loaded.normalisation
        self.threads = threads

    def refusal(self, window: SyncWindow, sample_rate: float, template_length: int) -> str | None:
        """Why this cell is outside what the network was trained on, or None."""
        config = self.model.config
        if abs(sample_rate - self.range.sample_rate) > 1e-6 * self.range.sample_rate:
            return f"sample rate {sample_rate:g} Hz, trained at {self.range.sample_rate:g} Hz"
        if (window.window_length, template_length) != (config.window_length, config.template_length):
            return (f"windows of {window.window_length} samples around a {template_length}-sample template, "
                    f"trained on {config.window_length} around {config.template_length}")
        if not np.all(np.isfinite(window.windows)):
            return "windows hold NaN or inf"
        if window.cosited_pci is not None and not self.range.cosited_pairs:
            return f"a co-sited pair (PCI {window.pci} with {window.cosited_pci}): not in the training data"
        if not self.range.min_frames <= window.n_frames <= self.range.max_frames:
            return f"{window.n_frames} frames, trained on {self.range.min_frames}..{self.range.max_frames}"
        per_frame = window.snr_db - 10 * math.log10(window.n_frames)
        if per_frame > self.range.max_snr_db:
            return f"per-frame SNR {per_frame:.1f} dB above the training range (<= {self.range.max_snr_db:.1f} dB)"
        return None

    def estimate(self, windows: list[np.ndarray], templates: list[np.ndarray]) -> list[tuple[float, float]]:
        """(offset, 1-sigma) in samples for each cell; cells with the same number of frames share a pass."""
        results: list[tuple[float, float] | None] = [None] * len(windows)
        by_frames: dict[int, list[int]] = {}
        for i, w in enumerate(windows):
            by_frames.setdefault(w.shape[0], []).append(i)
        previous = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            with torch.inference_mode():
                for members in by_frames.values():
                    signal, code = network_inputs(
                        torch.from_numpy(np.stack([windows[i] for i in members]).astype(np.float32)),
                        torch.from_numpy(np.stack([templates[i] for i in members]).astype(np.float32)),
                        self.normalisation)
                    offset, log_variance = self.model(signal, code)
                    sigma = torch.exp(0.5 * log_variance)
                    for i, o, s in zip(members, offset.tolist(), sigma.tolist()):
                        results[i] = (o, s)
        finally:
            torch.set_num_threads(previous)
        return results  # type: ignore[return-value]
