"""Cost of the timing network: FLOPs, parameters, and the time to time one stack's cells.

* FLOPs per inference (one cell, 10 frames), by torch's flop counter (the paper: 46 M).
* Batched inference of the 6 cells of one stack on one core: the network's forward pass alone,
  and the whole timing stage (normalisation, forward pass, amplitude, SNR and the Cramer-Rao
  bound per cell), against the stage with ML; median and 90th percentile over repeats.
* The same forward pass in onnxruntime (one thread) and its largest difference from torch.

Run:  .venv/bin/python benchmarks/speed/network_speed.py  [--checkpoint PATH] [--repeats 200]
Writes docs/results/timing_network/speed.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates, code_template
from deepsync.timing.checkpoint import load_checkpoint
from deepsync.timing.inputs import network_inputs
from deepsync.timing.model import count_flops
from deepsync.timing.network import DEFAULT_CHECKPOINT
from deepsync.timing.stage import Estimator, TimingConfig, TimingStage
from deepsync.types import SyncWindow

OUT = Path(__file__).resolve().parents[2] / "docs" / "results" / "timing_network" / "speed.json"
PCIS = (12, 97, 150, 301, 420, 488)


def timed(call, repeats: int) -> dict[str, float]:
    call()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    checkpoint = load_checkpoint(args.checkpoint)
    model = checkpoint.model
    frontend = FrontendConfig()
    templates = SyncTemplates(frontend)
    rng = np.random.default_rng(0)
    cells = [SyncWindow(0, pci, 1000, rng.normal(size=(10, 296)).astype(np.float32) * 1e-3, 10.0, -5.0)
             for pci in PCIS]
    signal, code = network_inputs(torch.from_numpy(np.stack([c.windows for c in cells])),
                                  torch.from_numpy(np.stack([code_template(templates, p) for p in PCIS]).astype(np.float32)),
                                  checkpoint.normalisation)

    def forward() -> None:
        with torch.inference_mode():
            model(signal, code)

    network_stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=args.checkpoint))
    ml_stage = TimingStage(frontend)
    result = {
        "checkpoint": str(args.checkpoint),
        "flops_per_inference_10_frames": count_flops(model, 10),
        "parameters": sum(p.numel() for p in model.parameters()),
        "cells_per_stack": len(cells),
        "torch_forward_6_cells_one_thread": timed(forward, args.repeats),
        "timing_stage_network_6_cells": timed(lambda: network_stage.process(cells), args.repeats),
        "timing_stage_ml_6_cells": timed(lambda: ml_stage.process(cells), max(20, args.repeats // 4)),
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, torch {torch.__version__}",
    }
    try:
        import onnxruntime

        from deepsync.timing.export import check_onnx, export_onnx
    except ModuleNotFoundError:
        result["onnx"] = "onnxruntime not installed"
    else:
        with tempfile.TemporaryDirectory() as scratch:
            path = export_onnx(checkpoint, Path(scratch) / "net.onnx")
            options = onnxruntime.SessionOptions()
            options.intra_op_num_threads = options.inter_op_num_threads = 1
            session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            feeds = {"windows": signal.numpy(), "template": code.numpy()}
            result["onnxruntime_forward_6_cells_one_thread"] = timed(lambda: session.run(None, feeds), args.repeats)
            result["onnx_vs_torch_max_abs_difference"] = check_onnx(path, checkpoint, trials=10)
    OUT.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
