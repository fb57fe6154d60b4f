"""The DeepSync timing network: a cell's stacked windows and its template in, a sub-sample
offset and an honest sigma out.

The paper's architecture (Ghosh et al., ICML 2025, section 4), sized for a tracker:

  windows (B, F, W) ──▶ [frame f, stack] ──▶ signal encoder, the same on every frame ──▶ mean over frames ──▶ Z (B, W/p, C)
  template (B, T)   ──▶ template encoder (its own weights)     ───────────────────────────────────────▶ H (B, T/p, C)
  cross-attention: Z queries, H keys and values ──▶ (B, W/p, C) ──▶ flatten ──▶ 3 dense layers
  ──▶ offset (B,) samples, log-variance (B,)

Each encoder is three 1-D convolutions with decreasing kernels (14, 7, 5), batch norm and ReLU,
with an average pool of ``pool`` samples after the first (fewer samples for the other two and
fewer tokens for the attention, whose cost grows with their square). Averaging the frames' feature
maps (temporal aggregation) rather than the frames themselves lets the encoder see each frame's
own fading before they are combined; but a nonlinear encoder on a frame that noise dominates
(the code sits at -20 dB per frame and below where ML breaks down) loses what coherent stacking
gains, so each frame enters the encoder as two channels: the frame, and the stack (the mean of
all frames, times sqrt(F) so it is in units of its own noise, as the frames are). The offset is
where the template's start lies in the windows, in samples from the windows' first sample,
minus the margin (``window_length - template_length) / 2``), i.e. relative to the coarse code
position the sync stage cut the windows at; the log-variance head gives the sigma the fusion
stage weighs it by. Attention keeps the template's position information through a learned
position embedding added to both token sequences.

Two choices beside the paper's, for its ablation and for what comes after it:

* ``fusion``: how the template's tokens meet the signal's. Cross-attention (the paper's), or the
  three the paper compared it with: concatenation and addition of the template's token at zero
  offset to each signal token, and correlation (the template's tokens slid along the signal's,
  per channel: one token per lag, a learned matched filter).
* ``head``: the paper's dense layers regress the offset from the flattened token map, so they
  must learn anew at every position what a code start looks like. ``soft_argmax`` lets every
  fused token vote instead: a score (softmax over the tokens) and where it puts the code's
  start, its own position (a signal token's, or where a lag puts the template's first token)
  plus a learned correction (a signal token inside the code can learn from what it attended to
  how far back the start lies). The offset is the scored mean of the votes, and moves with the
  code by construction; the dense layers still give the log-variance.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch
from torch import nn

from deepsync.schema import check_settings, resolve_choices, setting


LOG_VARIANCE_RANGE = (-12.0, 6.0)  # the sigma head's output is clamped to this: 0.0025 to 20 samples

MAX_PARAMETERS = 16_000_000
"""Weights a network may have (64 MB of float32; Adam keeps two more copies while training):
400 times the shipped network's."""


class Fusion(enum.Enum):
    """How the template's tokens meet the signal's (the paper's ablation, section 6)."""

    CROSS_ATTENTION = "cross_attention"  # signal tokens query the template's (the paper's choice)
    CONCATENATION = "concatenation"  # each signal token beside the template's token at zero offset
    ADDITION = "addition"  # the template's token at zero offset added to each signal token
    CORRELATION = "correlation"  # per channel, the template slid along the signal: one token per lag


class Head(enum.Enum):
    """How the fused tokens become an offset."""

    DENSE = "dense"  # the paper's: flatten, three dense layers
    SOFT_ARGMAX = "soft_argmax"  # each token votes for the code's start; the softmax of their scores weighs the votes


@dataclass(frozen=True)
class TimingNetConfig:
    """Sizes of the network; ``window_length`` and ``template_length`` are the sync stage's."""

    # Every size's range is far beyond what a sync stage's windows or a tracker's CPU ask for (the
    # shipped network: windows of 296 samples, 8-32 channels, 41,000 weights), and together with
    # MAX_PARAMETERS keeps a typo or a tampered checkpoint from allocating gigabytes before
    # anything else is checked. 4096 samples are 2 ms at 1.92 MS/s: a window is the code +- a margin.
    window_length: int = setting(296, help="W: samples per frame window (template + 2 x margin at 1.92 MS/s).",
                                 unit="samples", bounds=(1, 4096))
    template_length: int = setting(276, help="T: samples of the cell's code template.", unit="samples",
                                   bounds=(1, 4096))
    channels: tuple[int, int, int] = setting((8, 16, 32), help="Channels of each convolution; the last is the "
                                             "token width C.", bounds=(1, 1024))
    # decreasing: coarse shape first, then detail
    kernels: tuple[int, int, int] = setting((14, 7, 5), help="Kernel of each convolution.", unit="samples",
                                            bounds=(1, 256))
    pool: int = setting(2, help="Samples per token.", unit="samples", bounds=(1, 64))
    heads: int = setting(4, help="Attention heads; they divide the token width.", bounds=(1, 64))
    hidden: tuple[int, int] = setting((64, 32), help="Widths of the dense layers before the two outputs.",
                                      bounds=(1, 65536))
    dropout: float = setting(0.1, help="Dropout rate while training.", bounds=(0.0, 0.99))
    fusion: Fusion = setting(Fusion.CROSS_ATTENTION, help="How the template's tokens meet the signal's.",
                             choices={kind.value: kind for kind in Fusion})
    head: Head = setting(Head.DENSE, help="How the fused tokens become an offset.",
                         choices={kind.value: kind for kind in Head})

    def __post_init__(self) -> None:
        check_settings(self)
        resolve_choices(self)  # the names, as YAML and checkpoints hold them
        if self.channels[-1] % self.heads:
            raise ValueError(f"heads: {self.heads} must divide the token width channels[-1] = {self.channels[-1]}")
        if self.template_length > self.window_length:
            raise ValueError(f"template_length {self.template_length} is longer than window_length {self.window_length}")
        if self.pool > self.template_length:
            raise ValueError(f"pool {self.pool} is longer than template_length {self.template_length}: no token")
        if self.parameter_count > MAX_PARAMETERS:
            raise ValueError(f"a network of these sizes has {self.parameter_count:,} weights, more than the "
                             f"{MAX_PARAMETERS:,} allowed (the shipped one has about 41,000)")

    @property
    def parameter_count(self) -> int:
        """Weights of the network this config describes, counted without building it (a tested
        match for ``TimingNet``'s), so that a config is judged before anything is allocated."""
        width, fused = self.channels[-1], self.fused_tokens * self.fused_width

        def encoder(inputs: int) -> int:  # convolutions without bias, batch-norm scale and shift
            widths = (inputs, *self.channels)
            return sum(widths[i] * c * k + 2 * c for i, (c, k) in enumerate(zip(self.channels, self.kernels)))

        count = encoder(2) + encoder(1) + (self.signal_tokens + self.template_tokens) * width
        if self.fusion is Fusion.CROSS_ATTENTION:
            count += 4 * width * width + 4 * width  # in-projection of q, k, v and the out-projection, with biases
        inputs = fused
        for hidden in self.hidden:
            count += inputs * hidden + hidden
            inputs = hidden
        count += inputs + 1 if self.head is Head.DENSE else 2 * self.fused_width + 2
        return count + inputs + 1  # the log-variance

    def activation_bytes(self, frames: int) -> int:
        """About how much memory one example of ``frames`` frames takes through a training
        step (float32 feature maps of every layer of the encoders, attention weights, fused
        tokens; forward and backward): what sizes a batch."""
        maps = frames * self.window_length * (2 + 3 * sum(self.channels))
        attention = self.heads * self.signal_tokens * self.template_tokens
        return 4 * 2 * (maps + attention + self.fused_tokens * self.fused_width)

    @property
    def signal_tokens(self) -> int:
        return self.window_length // self.pool

    @property
    def template_tokens(self) -> int:
        return self.template_length // self.pool

    @property
    def fused_tokens(self) -> int:
        """Tokens after fusion: one per signal token, or one per lag for correlation."""
        if self.fusion is Fusion.CORRELATION:
            return self.signal_tokens - self.template_tokens + 1
        return self.signal_tokens

    @property
    def fused_width(self) -> int:
        return 2 * self.channels[-1] if self.fusion is Fusion.CONCATENATION else self.channels[-1]


def sinusoids(tokens: int, width: int, pool: int) -> torch.Tensor:
    """(tokens, width): sin and cos of each token's sample position at ``width // 2`` wavelengths
    from 4 samples to the window length, geometrically spaced."""
    position = torch.arange(tokens, dtype=torch.float32)[:, None] * pool
    wavelengths = 4.0 * (tokens * pool / 4.0) ** (torch.arange(width // 2, dtype=torch.float32) / max(1, width // 2 - 1))
    angle = 2 * torch.pi * position / wavelengths
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=1)


class Encoder(nn.Module):
    """(N, inputs, L) traces -> (N, L // pool, C) tokens: three convolutions that keep the length (an even
    kernel is padded one more sample after than before), each with batch norm and ReLU; the first
    sees every sample, the pool after it halves what the other two (most of the cost) process."""

    def __init__(self, config: TimingNetConfig, inputs: int = 1) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = inputs
        for i, (channels, kernel) in enumerate(zip(config.channels, config.kernels)):
            layers += [nn.ConstantPad1d(((kernel - 1) // 2, kernel // 2), 0.0),
                       nn.Conv1d(width, channels, kernel, bias=False), nn.BatchNorm1d(channels), nn.ReLU()]
            if i == 0:
                layers.append(nn.AvgPool1d(config.pool))
            width = channels
        self.net = nn.Sequential(*layers)

    def forward(self, traces: torch.Tensor) -> torch.Tensor:
        features = self.net(traces)  # (N, C, L // pool)
        return features.transpose(1, 2)  # (N, L // pool, C)


class TimingNet(nn.Module):
    """Offset (samples) and log-variance (samples^2) of a cell's code in its stacked windows."""

    def __init__(self, config: TimingNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or TimingNetConfig()
        c = self.config
        width = c.channels[-1]
        self.signal_encoder = Encoder(c, inputs=2)  # each frame beside the coherent stack
        self.template_encoder = Encoder(c)
        # the same sinusoids of the sample position in both: learnable, but from the start a
        # signal token and a template token can tell their relative offset
        self.signal_position = nn.Parameter(sinusoids(c.signal_tokens, width, c.pool))
        self.template_position = nn.Parameter(sinusoids(c.template_tokens, width, c.pool))
        if c.fusion is Fusion.CROSS_ATTENTION:
            self.attention = nn.MultiheadAttention(width, c.heads, batch_first=True)
        layers: list[nn.Module] = []
        inputs = c.fused_tokens * c.fused_width
        for hidden in c.hidden:
            layers += [nn.Linear(inputs, hidden), nn.ReLU(), nn.Dropout(c.dropout)]
            inputs = hidden
        self.regression = nn.Sequential(*layers)
        if c.head is Head.DENSE:
            self.offset = nn.Linear(inputs, 1)
        else:  # per token: a score and the correction to where it puts the code's start
            self.votes = nn.Linear(c.fused_width, 2)
            # the offset each fused token stands for: where it sits (the signal token's own
            # position, or where its lag puts the template's first token) less the margin
            margin = (c.window_length - c.template_length) / 2
            self.register_buffer("token_offset", torch.arange(c.fused_tokens, dtype=torch.float32) * c.pool - margin,
                                 persistent=False)
        self.log_variance = nn.Linear(inputs, 1)

    def forward(self, windows: torch.Tensor, template: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``windows`` (B, F, W) normalised volts, any number of frames F >= 1; ``template``
        (B, T) normalised; -> offset (B,) and log-variance (B,), within ``LOG_VARIANCE_RANGE``."""
        batch, frames, length = windows.shape
        stack = windows.mean(dim=1, keepdim=True) * frames**0.5  # (B, 1, W), in units of its own noise
        pairs = torch.stack([windows, stack.expand(-1, frames, -1)], dim=2)  # (B, F, 2, W)
        tokens = self.signal_encoder(pairs.reshape(batch * frames, 2, length))  # (B*F, W/p, C)
        signal = tokens.reshape(batch, frames, *tokens.shape[1:]).mean(dim=1)  # (B, W/p, C)
        signal = signal + self.signal_position
        code = self.template_encoder(template.unsqueeze(1)) + self.template_position  # (B, T/p, C)
        fused = self.fuse(signal, code)  # (B, N, D): N fused tokens of width D
        hidden = self.regression(fused.flatten(1))  # (B, hidden[-1])
        log_variance = self.log_variance(hidden).squeeze(-1).clamp(*LOG_VARIANCE_RANGE)
        if self.config.head is Head.DENSE:
            return self.offset(hidden).squeeze(-1), log_variance
        score, correction = self.votes(fused).unbind(-1)  # (B, N) each
        offset = (torch.softmax(score, dim=1) * (self.token_offset + correction)).sum(dim=1)  # (B,)
        return offset, log_variance

    def sigma_head(self) -> nn.Module:
        """What only the log-variance depends on: with the soft-argmax head the dense layers too
        (the offset comes from the votes), with the dense head its last layer alone."""
        if self.config.head is Head.DENSE:
            return self.log_variance
        return nn.ModuleList([self.regression, self.log_variance])

    def fuse(self, signal: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Signal tokens (B, S, C) and template tokens (B, K, C) -> fused tokens (B, N, D)."""
        fusion = self.config.fusion
        if fusion is Fusion.CROSS_ATTENTION:
            return self.attention(signal, code, code, need_weights=False)[0]  # (B, S, C)
        if fusion is Fusion.CORRELATION:
            lags = signal.unfold(1, code.shape[1], 1)  # (B, S-K+1, C, K): the signal under each lag
            return torch.einsum("blck,bkc->blc", lags, code) / code.shape[1]  # (B, S-K+1, C)
        # the template's tokens where a code at zero offset would lie in the signal's
        before = (self.config.window_length - self.config.template_length) // 2 // self.config.pool
        placed = nn.functional.pad(code, (0, 0, before, signal.shape[1] - code.shape[1] - before))  # (B, S, C)
        if fusion is Fusion.ADDITION:
            return signal + placed  # (B, S, C)
        return torch.cat([signal, placed], dim=-1)  # (B, S, 2C)


def count_flops(model: TimingNet, frames: int = 10) -> int:
    """Floating-point operations of one inference (one cell, ``frames`` frames), by torch's counter
    (a multiply-add counts 2)."""
    from torch.utils.flop_counter import FlopCounterMode

    c = model.config
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad(), FlopCounterMode(display=False) as counter:
            model(torch.zeros(1, frames, c.window_length), torch.zeros(1, c.template_length))
    finally:
        model.train(was_training)
    return int(counter.get_total_flops())
