"""Timing-network checkpoints: written and read back with nothing but tensors and plain values.

A checkpoint holds the network's weights, its :class:`~deepsync.timing.model.TimingNetConfig`,
the input normalisation it was trained with and the range of inputs it was trained on (so the
timing stage can tell when a cell lies outside it), plus the optimiser state and step when it
is a training checkpoint to resume. It is read with ``torch.load(..., weights_only=True)``:
torch's restricted unpickler builds tensors, numbers, strings, lists and dicts, and refuses any
other object, so a tampered file cannot run code. Everything is then checked against what this
code expects (format version, config fields, the weights' names and shapes), and a checkpoint
that does not match is refused with the reason, never half-loaded.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from deepsync.outputs import replacing
from deepsync.timing.inputs import Normalisation
from deepsync.timing.model import TimingNet, TimingNetConfig

FORMAT = "deepsync-timing-net"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: the message names the file and the cause."""


@dataclass(frozen=True)
class TrainingRange:
    """The inputs a network was trained on; outside them the timing stage does not trust it."""

    sample_rate: float  # Hz: the templates' and windows' rate
    min_frames: int
    max_frames: int
    min_snr_db: float  # per frame, before stacking
    max_snr_db: float
    cosited_pairs: bool  # whether co-sited pairs' combined templates were among the examples

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sample_rate) and self.sample_rate > 0):
            raise ValueError(f"sample_rate: {self.sample_rate!r} must be a positive number of Hz")
        if not 1 <= self.min_frames <= self.max_frames:
            raise ValueError(f"min_frames {self.min_frames!r} and max_frames {self.max_frames!r}: 1 <= min <= max")
        if not self.min_snr_db <= self.max_snr_db:
            raise ValueError(f"min_snr_db {self.min_snr_db!r} must not exceed max_snr_db {self.max_snr_db!r}")


@dataclass(frozen=True)
class TimingCheckpoint:
    """A network ready to run (eval mode), and what it was trained on and for how long."""

    model: TimingNet
    training_range: TrainingRange
    normalisation: Normalisation  # how its inputs must be scaled (``timing.inputs``)
    step: int  # optimiser steps taken
    optimiser: dict[str, Any] | None  # Adam's state, to resume training
    meta: dict[str, Any]  # how it was made (config file, seed, command): strings and numbers


def _plain(value: object) -> object:
    """Dataclass fields as what weights_only loading rebuilds: tuples become lists, choices their names."""
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, enum.Enum):
        return value.value
    return value


def save_checkpoint(path: str | Path, model: TimingNet, training_range: TrainingRange,
                    normalisation: Normalisation, *, step: int = 0,
                    optimiser: dict[str, Any] | None = None, meta: dict[str, Any] | None = None) -> None:
    """Write a checkpoint atomically (a crash leaves the previous file, or none)."""
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": {k: _plain(v) for k, v in dataclasses.asdict(model.config).items()},
        "training_range": dataclasses.asdict(training_range),
        "normalisation": dataclasses.asdict(normalisation),
        "state_dict": {name: tensor.detach().cpu() for name, tensor in model.state_dict().items()},
        "step": int(step),
        "optimiser": optimiser,
        "meta": dict(meta or {}),
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as temporary:
        torch.save(payload, temporary)


def _field(payload: dict, key: str, kind: type, where: str) -> Any:
    if key not in payload:
        raise CheckpointError(f"{where}: no {key!r} (not a DeepSync timing-network checkpoint?)")
    value = payload[key]
    if not isinstance(value, kind):
        raise CheckpointError(f"{where}: {key!r} is a {type(value).__name__}, expected {kind.__name__}")
    return value


def _dataclass(cls: type, values: dict, where: str) -> Any:
    names = {f.name for f in dataclasses.fields(cls)}
    unknown, missing = sorted(set(values) - names), sorted(names - set(values))
    if unknown or missing:
        raise CheckpointError(f"{where}: {cls.__name__} does not match this version of deepsync "
                              f"(unknown: {', '.join(unknown) or 'none'}; missing: {', '.join(missing) or 'none'})")
    typed = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    try:
        return cls(**typed)
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{where}: {cls.__name__}: {error}") from None


def load_checkpoint(path: str | Path) -> TimingCheckpoint:
    """Read and check a checkpoint; CheckpointError naming the file and the cause."""
    where = os.fspath(path)
    try:
        payload = torch.load(where, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"{where}: no such file") from None
    except Exception as error:  # noqa: BLE001 - torch's parsers raise many kinds (IndexError for a YAML file)
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise CheckpointError(f"{where}: not a loadable checkpoint (torch.load with weights_only=True: {first})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{where}: holds a {type(payload).__name__}, not a checkpoint")
    if payload.get("format") != FORMAT:
        raise CheckpointError(f"{where}: format {payload.get('format')!r}, expected {FORMAT!r}")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"{where}: format version {payload.get('version')!r}; this deepsync reads {VERSION}")
    config = _dataclass(TimingNetConfig, _field(payload, "config", dict, where), f"{where}: config")
    training_range = _dataclass(TrainingRange, _field(payload, "training_range", dict, where),
                                f"{where}: training_range")
    normalisation = _dataclass(Normalisation, _field(payload, "normalisation", dict, where),
                               f"{where}: normalisation")
    state = _field(payload, "state_dict", dict, where)
    model = TimingNet(config)
    expected = model.state_dict()
    unknown, missing = sorted(set(state) - set(expected)), sorted(set(expected) - set(state))
    if unknown or missing:
        raise CheckpointError(f"{where}: weights do not match the network its config describes (unknown: "
                              f"{', '.join(unknown[:5]) or 'none'}; missing: {', '.join(missing[:5]) or 'none'})")
    for name, tensor in state.items():
        if not isinstance(tensor, torch.Tensor) or tensor.shape != expected[name].shape:
            shape = tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else type(tensor).__name__
            raise CheckpointError(f"{where}: weight {name} is {shape}, the config needs {tuple(expected[name].shape)}")
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise CheckpointError(f"{where}: weight {name} holds NaN or inf")
    model.load_state_dict(state)
    model.eval()
    step = _field(payload, "step", int, where)
    optimiser = payload.get("optimiser")
    if optimiser is not None and not isinstance(optimiser, dict):
        raise CheckpointError(f"{where}: 'optimiser' is a {type(optimiser).__name__}, expected a dict or None")
    return TimingCheckpoint(model, training_range, normalisation, step, optimiser, _field(payload, "meta", dict, where))
