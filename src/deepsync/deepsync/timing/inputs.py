"""What the timing network sees: windows in units of their own per-frame noise, a unit template.

Both training and inference go through :func:`network_inputs`, so the two cannot differ.

* Windows: each row's mean (the load-dependent pedestal, the AC coupling's wander) is removed,
  then the example is divided by its per-frame interference RMS, measured as the estimators
  measure it: the frame-to-frame fluctuation around the row mean (``n / (n - 1)`` corrected).
  The code then stands out by its true per-frame SNR whatever the gain, the received power or
  the number of frames, which is what the sigma head needs to see. Finally a global
  ``window_scale`` (from the training set, stored in the checkpoint) brings the values near
  unit variance.
* Template: mean removed, unit RMS (its scale is volts per watt, meaningless to the network).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

@dataclass(frozen=True)
class Normalisation:
    """Global scale of the noise-normalised windows, measured on the training set."""

    window_scale: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_scale) and self.window_scale > 0):
            raise ValueError(f"window_scale: {self.window_scale!r} must be a positive number")


def noise_normalised(windows: torch.Tensor) -> torch.Tensor:
    """(B, F, W) volts, F >= 2 -> (B, F, W) in units of each example's per-frame noise RMS."""
    rows = windows - windows.mean(dim=2, keepdim=True)
    frames = rows.shape[1]
    residual = rows - rows.mean(dim=1, keepdim=True)
    variance = residual.pow(2).mean(dim=(1, 2)) * frames / (frames - 1)  # (B,)
    # per example: one dead or corrupt window must not change the others of its batch
    scale = variance.clamp_min(torch.finfo(variance.dtype).tiny).sqrt()
    return rows / scale[:, None, None]


def unit_template(template: torch.Tensor) -> torch.Tensor:
    """(B, T) -> zero mean, unit RMS."""
    centred = template - template.mean(dim=1, keepdim=True)
    return centred / centred.pow(2).mean(dim=1, keepdim=True).sqrt().clamp_min(1e-30)


def network_inputs(windows: torch.Tensor, template: torch.Tensor,
                   normalisation: Normalisation) -> tuple[torch.Tensor, torch.Tensor]:
    """The network's two inputs from raw windows (B, F, W) and templates (B, T)."""
    return noise_normalised(windows) / normalisation.window_scale, unit_template(template)
