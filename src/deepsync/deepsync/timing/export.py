"""The timing network as ONNX, for trackers that run onnxruntime instead of torch.

The graph is the network alone, with the batch and the number of frames dynamic: inputs
``windows`` (B, F, W) and ``template`` (B, T) already normalised as ``timing.inputs``
describes (row means removed, divided by the per-frame noise RMS and by ``window_scale``;
template zero-mean, unit RMS), outputs ``offset`` and ``log_variance`` (B,). ``window_scale``
and the training range travel in the model's metadata, so the file alone says how to feed it.
:func:`check_onnx` runs it in onnxruntime against torch on random inputs.
"""

from __future__ import annotations

import dataclasses
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from deepsync.outputs import check_writable, replacing
from deepsync.timing.checkpoint import TimingCheckpoint

MAX_BATCH = 1024
MAX_FRAMES = 1000


def export_onnx(checkpoint: TimingCheckpoint, path: str | Path) -> Path:
    """Write the checkpoint's network to ``path`` (opset chosen by torch's exporter) as one
    self-contained file, replaced whole or not at all: the exporter works in a temporary folder
    (its weights file, ``.onnx.data``, is folded into the graph and goes with it), and a
    folder that cannot be written is refused before the export's minute of work."""
    import onnx

    path = check_writable(path, "ONNX model")
    model = checkpoint.model.eval()
    c = model.config
    example = (torch.zeros(2, 10, c.window_length), torch.zeros(2, c.template_length))
    batch = torch.export.Dim("batch", min=1, max=MAX_BATCH)
    frames = torch.export.Dim("frames", min=2, max=MAX_FRAMES)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{path.name}.", dir=path.parent) as work:
        exported = Path(work) / "model.onnx"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's notes on its own internals
            torch.onnx.export(model, example, str(exported), input_names=["windows", "template"],
                              output_names=["offset", "log_variance"], dynamo=True, verbose=False,
                              dynamic_shapes={"windows": {0: batch, 1: frames}, "template": {0: batch}})
        graph = onnx.load(str(exported))  # with the weights of an external .onnx.data, if it wrote one
    metadata = {"window_scale": checkpoint.normalisation.window_scale,
                **{f"training_range.{k}": v for k, v in dataclasses.asdict(checkpoint.training_range).items()}}
    for key, value in metadata.items():
        entry = graph.metadata_props.add()
        entry.key, entry.value = key, str(value)
    with replacing(path) as temporary:
        onnx.save(graph, str(temporary), save_as_external_data=False)
    return path


def check_onnx(path: str | Path, checkpoint: TimingCheckpoint, trials: int = 5, seed: int = 0) -> float:
    """Largest |onnxruntime - torch| over both outputs on random inputs of varying batch and frames."""
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    c = checkpoint.model.config
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(trials):
        batch, frames = int(rng.integers(1, 9)), int(rng.integers(2, 41))
        windows = rng.standard_normal((batch, frames, c.window_length)).astype(np.float32)
        template = rng.standard_normal((batch, c.template_length)).astype(np.float32)
        ours = session.run(None, {"windows": windows, "template": template})
        with torch.no_grad():
            theirs = checkpoint.model(torch.from_numpy(windows), torch.from_numpy(template))
        worst = max(worst, *(float(np.max(np.abs(a - b.numpy()))) for a, b in zip(ours, theirs)))
    return worst
