"""Training the timing network: ``deepsync train --config config/timing/timing_net.yaml``.

Read top to bottom: the config (three sections: ``dataset``, ``model``, ``training``), the data
(made first if shards are missing, then held in memory), the loss, the loop. Each step draws a
batch and a number of frames F (``min_frames..max_frames``), and gives every example F of its
frames picked at random (the model takes any F; a different subset each time is free
augmentation). Loss: Huber (delta ``huber_delta`` samples) on the offset of the examples whose
code is at least ``huber_min_stacked_snr_db`` after stacking, plus ``nll_weight``
times the Gaussian negative log-likelihood of the error under the predicted variance, with the
error detached there so the sigma head learns how wrong the offset is without pulling the offset
towards easy examples. Adam with a linear warm-up and a cosine decay (the paper's 1e-4 constant
rate needs far more steps than a CPU hour gives).

Then ``calibration_steps`` more steps calibrate the sigma: the best checkpoint's sigma head
alone (the dense layers after the fusion; encoders, batch norms and the offset frozen, so every
offset stays as it was) learns the 68.3 % quantile of the error's size given the input, by the
pinball loss on log |error|. The Gaussian NLL fits the error's variance, and where errors are a
narrow core and a tail of wrong lobes, a sigma from the variance holds 75-85 % of them, not the
68 % a 1-sigma should (``docs/design/timing_network.md``).

Interrupt at any time: ``<run_dir>/last.pt`` (saved every ``eval_every`` steps, with the
optimiser) is where a rerun resumes, and every batch is drawn from ``(seed, step, rank)``, so a
resumed run takes the same path as an uninterrupted one. The checkpoint with the lowest
validation RMSE over the examples with a code to find (at least ``huber_min_stacked_snr_db``
after stacking 10 frames) is kept as ``<run_dir>/best.pt`` (no optimiser: the file to ship), and
again with its sigma calibrated; the curve to ``<run_dir>/training_curve.png`` and
``history.json``, each replaced whole. ``best.pt`` is the run's network; only a finished run
copies it to ``model_path`` where one is set, so an interrupted one leaves the file there as it
was. The shipped network's file is replaced only when asked (``replace_shipped``,
``deepsync train --replace-shipped``): a copied config that still names it is refused.

Devices: a GPU when there is one, else the CPU. Under ``torchrun`` every rank trains on its own
batches and DistributedDataParallel averages the gradients; rank 0 evaluates and writes, and
calibrates the sigma alone (a small head: minutes on a CPU).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from deepsync.configio import ConfigError, build_dataclass, choice_name, load_yaml, require_mapping
from deepsync.frontend.config import FrontendConfig
from deepsync.outputs import check_writable, replacing, write_text
from deepsync.schema import check_settings, setting
from deepsync.timing.checkpoint import TrainingRange, load_checkpoint, save_checkpoint
from deepsync.timing.estimators import SIGMA_CALIBRATION_BAND
from deepsync.timing.inputs import Normalisation, network_inputs, noise_normalised
from deepsync.timing.model import TimingNet, TimingNetConfig
from deepsync.timing.network import DEFAULT_CHECKPOINT
from deepsync.training.dataset import DatasetConfig, generate, load_split


MAX_BATCH_BYTES = 8 * 2**30
"""Memory a training batch may take (``TimingNetConfig.activation_bytes`` of its examples at
``max_frames``): the shipped run's batches take about 0.7 GB."""
MAX_DATASET_BYTES = 16 * 2**30
"""Memory the training and validation examples may take, held in memory as float32 windows,
templates and mean frames: the shipped run's take about 0.3 GB."""


@dataclass(frozen=True)
class TrainConfig:
    # Ranges: a value outside is a typo or a unit slip; left through, it trains for hours and then
    # fails (steps 1e308), or fails at the first step (huber_delta 0, threads -1), or makes every
    # weight NaN (learning_rate 1e308).
    data_dir: str = setting("data/timing", help="Where the examples' shards are (made there when missing).")
    train_shards: int = setting(80, help="Shards of the training split.", unit="shards", bounds=(1, 100_000))
    val_shards: int = setting(6, help="Shards of the validation split.", unit="shards", bounds=(1, 10_000))
    test_shards: int = setting(8, help="Shards of the test split (made, never trained on).", unit="shards",
                               bounds=(0, 10_000))
    run_dir: str = setting("runs/timing", help="Where the run writes last.pt, best.pt and its curve.")
    model_path: str = setting("", help="Where a finished run copies best.pt; empty: nowhere (the network is "
                              "<run_dir>/best.pt).")
    # the shipped network took 8000
    steps: int = setting(10000, help="Training steps before the sigma calibration.", unit="steps",
                         bounds=(1, 10_000_000))
    # and within MAX_BATCH_BYTES (RunConfig)
    batch_size: int = setting(128, help="Examples per step.", unit="examples", bounds=(1, 65_536))
    # Adam's steps are about this size: beyond 1 every weight diverges
    learning_rate: float = setting(1e-3, help="Adam's learning rate after the warm-up.", bounds=(1e-9, 1.0))
    final_learning_rate: float = setting(1e-5, help="Learning rate the cosine decay ends at.", bounds=(1e-12, 1.0))
    warmup_steps: int = setting(200, help="Steps of the linear warm-up.", unit="steps", bounds=(0, 10_000_000))
    min_frames: int = setting(4, help="Fewest frames a batch is given.", unit="frames", bounds=(2, 100))
    max_frames: int = setting(12, help="Most frames a batch is given (at most the dataset's).", unit="frames",
                              bounds=(2, 100))
    # 0 is no loss at all (torch refuses it)
    huber_delta: float = setting(1.0, help="Huber loss's delta on the offset.", unit="samples", bounds=(1e-3, 1000.0))
    nll_weight: float = setting(0.5, help="Weight of the Gaussian negative log-likelihood beside the Huber loss.",
                                bounds=(0.0, 1000.0))
    # examples whose code is weaker than this after stacking carry no offset to learn (a random sign
    # of Huber gradient per example, drowning the rest): they train the sigma head only
    huber_min_stacked_snr_db: float = setting(-15.0, help="Stacked SNR below which an example trains the sigma "
                                              "head only.", unit="dB", bounds=(-100.0, 100.0))
    eval_every: int = setting(250, help="Steps between validations (and saves of last.pt).", unit="steps",
                              bounds=(1, 10_000_000))
    # after ``steps``: the sigma head alone, fitted to the 68.3 % quantile of |error| (module docstring)
    calibration_steps: int = setting(3000, help="Steps calibrating the sigma head alone.", unit="steps",
                                     bounds=(0, 10_000_000))
    calibration_learning_rate: float = setting(3e-4, help="Learning rate of the sigma calibration.",
                                               bounds=(1e-12, 1.0))
    seed: int = setting(7, help="Seed every batch is drawn from (with its step and rank).", bounds=(0, 2**63 - 1))
    threads: int = setting(0, help="CPU threads for torch; 0: torch's default.", unit="threads", bounds=(0, 1024))
    workers: int = setting(2, help="Processes making missing shards.", unit="processes", bounds=(1, 64))

    def __post_init__(self) -> None:
        check_settings(self)
        if not 2 <= self.min_frames <= self.max_frames:
            raise ValueError(f"min_frames {self.min_frames} and max_frames {self.max_frames}: 2 <= min <= max "
                             "(the windows are normalised by their frame-to-frame noise)")
        if not 0 < self.final_learning_rate <= self.learning_rate:
            raise ValueError(f"learning rates: 0 < final_learning_rate {self.final_learning_rate!r} <= "
                             f"learning_rate {self.learning_rate!r}")


@dataclass(frozen=True)
class RunConfig:
    dataset: DatasetConfig
    model: TimingNetConfig
    training: TrainConfig

    def __post_init__(self) -> None:
        if self.training.max_frames > self.dataset.max_frames:
            raise ValueError(f"training.max_frames {self.training.max_frames} exceeds the examples' "
                             f"dataset.max_frames {self.dataset.max_frames}")
        window = 2 * self.dataset.window_margin + self.model.template_length
        if window != self.model.window_length:
            raise ValueError(f"model.window_length {self.model.window_length} must be the examples' "
                             f"template + 2 x dataset.window_margin = {window}")
        # sizes checked against their bounds before anything is allocated
        batch = self.training.batch_size * self.model.activation_bytes(self.training.max_frames)
        if batch > MAX_BATCH_BYTES:
            most = MAX_BATCH_BYTES // self.model.activation_bytes(self.training.max_frames)
            raise ValueError(f"training.batch_size {self.training.batch_size}: a batch would take about "
                             f"{batch / 2**30:.3g} GiB, beyond the {MAX_BATCH_BYTES / 2**30:g} GiB bound "
                             f"(at most {most} examples of {self.training.max_frames} frames with this model)")
        shards = self.training.train_shards + self.training.val_shards
        held = shards * self.dataset.examples_per_shard * self.dataset.example_bytes(self.model.template_length)
        if held > MAX_DATASET_BYTES:
            raise ValueError(f"{self.training.train_shards} + {self.training.val_shards} shards of "
                             f"{self.dataset.examples_per_shard} examples would hold about {held / 2**30:.3g} GiB "
                             f"in memory, beyond the {MAX_DATASET_BYTES / 2**30:g} GiB bound")


def load_run_config(path: str | Path) -> RunConfig:
    """The YAML's three sections as typed configs; ConfigError naming the field."""
    data = require_mapping(load_yaml(path), str(path))
    unknown = sorted(set(data) - {"dataset", "model", "training"})
    if unknown:
        raise ConfigError(f"{path}: unknown section {', '.join(unknown)} (known: dataset, model, training)")
    sections = {name: build_dataclass(cls, data.get(name, {}), f"{path}: {name}")
                for name, cls in (("dataset", DatasetConfig), ("model", TimingNetConfig), ("training", TrainConfig))}
    try:
        return RunConfig(**sections)
    except ValueError as error:
        raise ConfigError(f"{path}: {error}") from None


# -- data --------------------------------------------------------------------------------------


class Examples:
    """One split in memory: raw windows (N, max_frames, W), templates (N, T), offsets (N,)."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self.windows = torch.from_numpy(arrays["windows"])
        self.template = torch.from_numpy(arrays["template"])
        self.offset = torch.from_numpy(arrays["offset"].astype(np.float32))
        self.snr_db = arrays["snr_db"]  # per frame
        self.has_pairs = bool(np.any(arrays["cosited_pci"] >= 0))  # co-sited pairs with their fitted model

    def __len__(self) -> int:
        return len(self.offset)

    def batch(self, rng: np.random.Generator, size: int, frames: int) -> tuple[torch.Tensor, ...]:
        """``size`` random examples, each with ``frames`` of its frames picked at random: windows,
        templates, offsets and the stacked SNR (dB)."""
        index = rng.integers(len(self), size=size)
        picks = np.argsort(rng.random((size, self.windows.shape[1])), axis=1)[:, :frames]
        windows = self.windows[torch.from_numpy(index)[:, None], torch.from_numpy(picks)]
        stacked_snr = torch.from_numpy(self.snr_db[index] + 10 * np.log10(frames)).float()
        return windows, self.template[index], self.offset[index], stacked_snr


def measure_normalisation(examples: Examples, frames: int) -> Normalisation:
    """The global window scale: RMS of noise-normalised windows over (up to) 2000 examples."""
    sample = noise_normalised(examples.windows[:2000, :frames])
    return Normalisation(float(sample.pow(2).mean().sqrt()))


def training_range(run: RunConfig, examples: Examples) -> TrainingRange:
    low, high = np.percentile(examples.snr_db, [1, 99])
    return TrainingRange(FrontendConfig().adc_rate_hz, run.training.min_frames, run.training.max_frames,
                         float(low), float(high), cosited_pairs=examples.has_pairs)


# -- loss and schedule -----------------------------------------------------------------------


def loss_terms(offset: torch.Tensor, log_variance: torch.Tensor, target: torch.Tensor, stacked_snr_db: torch.Tensor,
               config: TrainConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(Huber on the offset of the examples with a code to find, Gaussian NLL of every
    example's detached error under its predicted variance)."""
    useful = (stacked_snr_db >= config.huber_min_stacked_snr_db).float()
    huber = (F.huber_loss(offset, target, delta=config.huber_delta, reduction="none") * useful).sum()
    huber = huber / useful.sum().clamp_min(1.0)
    error = (offset.detach() - target).pow(2)
    nll = 0.5 * (log_variance + error * torch.exp(-log_variance)).mean()
    return huber, nll


# the share of a Gaussian's errors within +-1 sigma: what the calibrated sigma holds
SIGMA_QUANTILE = math.erf(1 / math.sqrt(2))


def quantile_loss(log_variance: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
    """Pinball loss of log sigma against log |error|, least where sigma is the ``SIGMA_QUANTILE``
    of |error| given the input (log: one scale from 0.01 to 10 samples; 1e-3 samples keeps an
    exact hit finite)."""
    residual = torch.log(error.abs() + 1e-3) - 0.5 * log_variance
    return torch.maximum(SIGMA_QUANTILE * residual, (SIGMA_QUANTILE - 1) * residual).mean()


def learning_rate(step: int, config: TrainConfig) -> float:
    if step < config.warmup_steps:
        return config.learning_rate * (step + 1) / config.warmup_steps
    progress = min(1.0, (step - config.warmup_steps) / max(1, config.steps - config.warmup_steps))
    cosine = 0.5 * (1 + math.cos(math.pi * progress))
    return config.final_learning_rate + (config.learning_rate - config.final_learning_rate) * cosine


@torch.no_grad()
def evaluate(model: TimingNet, examples: Examples, normalisation: Normalisation, frames: int,
             device: torch.device, min_stacked_snr_db: float, batch: int = 512) -> dict[str, float]:
    """Median / RMS error and sigma calibration on the first ``frames`` frames of every example,
    and the RMS error of the examples whose code is at least ``min_stacked_snr_db`` after
    stacking (those the offset is trained on; below, every estimator guesses a lobe)."""
    model.eval()
    errors, sigmas = [], []
    for start in range(0, len(examples), batch):
        windows, template = network_inputs(examples.windows[start : start + batch, :frames],
                                           examples.template[start : start + batch], normalisation)
        offset, log_variance = model(windows.to(device), template.to(device))
        errors.append(offset.cpu() - examples.offset[start : start + batch])
        sigmas.append(torch.exp(0.5 * log_variance).cpu())
    model.train()
    error, sigma = torch.cat(errors).abs(), torch.cat(sigmas)
    coded = torch.from_numpy(examples.snr_db + 10 * np.log10(frames) >= min_stacked_snr_db)
    rmse = float(error.pow(2).mean().sqrt())
    return {"median_abs_error": float(error.median()), "rmse": rmse,
            # no code to find in the whole split: every example then (else NaN, and no checkpoint)
            "rmse_with_code": float(error[coded].pow(2).mean().sqrt()) if coded.any() else rmse,
            "within_1_sigma": float((error <= sigma).float().mean())}


# -- the loop ----------------------------------------------------------------------------------


def destination(cfg: TrainConfig, replace_shipped: bool = False) -> Path | None:
    """Where a finished run copies its best checkpoint (None: it stays in the run directory):
    ``model_path``, or with ``replace_shipped`` the shipped network's file; ValueError where
    ``model_path`` names the shipped file unasked, or another file than the one asked for."""
    shipped = DEFAULT_CHECKPOINT.resolve()
    named = Path(cfg.model_path).resolve() if cfg.model_path else None
    if replace_shipped:
        if named not in (None, shipped):
            raise ValueError(f"--replace-shipped replaces {DEFAULT_CHECKPOINT}, but training.model_path names "
                             f"{cfg.model_path}: remove one of them")
        return DEFAULT_CHECKPOINT
    if named == shipped:
        raise ValueError(f"training.model_path is the shipped network ({cfg.model_path}): add --replace-shipped to "
                         f"replace it, or remove the line (the run's network is then {Path(cfg.run_dir) / BEST})")
    return None if named is None else Path(cfg.model_path)


def train(run: RunConfig, config_path: str = "", replace_shipped: bool = False) -> Path:
    """Train (or resume) as ``run`` says; returns the path of the trained network (the best
    checkpoint, or where ``destination`` copied it)."""
    cfg = run.training
    shipping = destination(cfg, replace_shipped)
    if shipping is not None:
        check_writable(shipping, "trained network")  # at the door, not after an hour of training
    check_writable(Path(cfg.run_dir) / "last.pt", "run's checkpoints")
    distributed = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
    rank = int(os.environ.get("RANK", 0))
    if distributed:
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    root = Path(cfg.data_dir)
    if rank == 0:
        generate(root, {"train": cfg.train_shards, "val": cfg.val_shards, "test": cfg.test_shards}, run.dataset,
                 workers=cfg.workers)
    if distributed:
        torch.distributed.barrier()
    # the shards the config counts (and MAX_DATASET_BYTES bounds), whatever else the folder holds
    train_set = Examples(load_split(root, "train", cfg.train_shards))
    val_set = Examples(load_split(root, "val", cfg.val_shards))
    normalisation = measure_normalisation(train_set, min(10, cfg.max_frames))
    trained_on = training_range(run, train_set)

    torch.manual_seed(cfg.seed)
    model = TimingNet(run.model).to(device)
    optimiser = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate)
    run_dir = Path(cfg.run_dir)
    last = run_dir / "last.pt"
    history: list[dict] = []
    step = 0
    calibrating_since = None  # the step the sigma's calibration started at, where last.pt is mid-way
    if last.exists():
        if not (run_dir / BEST).exists() and shipping is not None and shipping.exists():
            shutil.copyfile(shipping, run_dir / BEST)  # a run from before best.pt kept its best there
        resumed = load_checkpoint(last)
        if resumed.model.config != run.model:
            raise ValueError(f"{last} is a run of another model config ({resumed.model.config}): remove "
                             f"{run_dir} or choose another training.run_dir")
        model.load_state_dict(resumed.model.state_dict())
        optimiser.load_state_dict(resumed.optimiser)
        step = resumed.step
        calibrating_since = resumed.meta.get("calibrating_since_step")
        if calibrating_since is not None and cfg.steps > calibrating_since:
            raise ValueError(f"{last} is calibrating its sigma since step {calibrating_since}: more training steps "
                             f"({cfg.steps}) would train a calibrated network; remove {run_dir} to train anew")
        history = read_history(run_dir / "history.json")
        if rank == 0:
            print(f"resuming {last} at step {step}")
    net = torch.nn.parallel.DistributedDataParallel(model) if distributed else model
    meta = {"config": str(config_path),
            "run": json.dumps(asdict(run), default=choice_name),
            "examples": len(train_set), "normalisation": json.dumps(asdict(normalisation))}
    # the checkpoint to ship: the best RMSE where there is a code to find (the RMSE over every
    # example is the undetectable ones' guessing, and rises while the median still falls)
    best = min((h["val_rmse_with_code"] for h in history if "val_rmse_with_code" in h), default=math.inf)
    model.train()
    started = time.monotonic()
    with tqdm(total=cfg.steps, initial=step, desc="training", unit="step", disable=rank != 0) as bar:
        while step < cfg.steps:
            rng = np.random.default_rng([cfg.seed, step, rank])
            torch.manual_seed(int(rng.integers(2**62)))  # dropout's draws: from the step too, for resuming
            frames = int(rng.integers(cfg.min_frames, cfg.max_frames + 1))
            windows, template, target, stacked_snr = train_set.batch(rng, cfg.batch_size, frames)
            windows, template = network_inputs(windows, template, normalisation)
            offset, log_variance = net(windows.to(device), template.to(device))
            huber, nll = loss_terms(offset, log_variance, target.to(device), stacked_snr.to(device), cfg)
            for group in optimiser.param_groups:
                group["lr"] = learning_rate(step, cfg)
            optimiser.zero_grad(set_to_none=True)
            (huber + cfg.nll_weight * nll).backward()
            optimiser.step()
            step += 1
            bar.update(1)
            if rank == 0 and (step % cfg.eval_every == 0 or step == cfg.steps):
                scores = evaluate(model, val_set, normalisation, min(10, cfg.max_frames), device,
                                  cfg.huber_min_stacked_snr_db)
                history.append({"step": step, "huber": huber.item(), "nll": nll.item(), "lr": learning_rate(step, cfg),
                                "seconds": time.monotonic() - started,
                                **{f"val_{k}": v for k, v in scores.items()}})
                bar.set_postfix(val_rmse=f"{scores['rmse']:.3f}", val_med=f"{scores['median_abs_error']:.3f}")
                if scores["rmse_with_code"] < best:
                    best = scores["rmse_with_code"]
                    save_checkpoint(run_dir / BEST, model, trained_on, normalisation, step=step, meta=meta)
                save_checkpoint(last, model, trained_on, normalisation, step=step,
                                optimiser=optimiser.state_dict(), meta=meta)
                write_history(history, run_dir)
    if distributed:
        torch.distributed.destroy_process_group()
    since = step if calibrating_since is None else calibrating_since
    if rank == 0 and step < since + cfg.calibration_steps:
        if calibrating_since is None:  # its start: the best checkpoint, a fresh optimiser
            model.load_state_dict(load_checkpoint(run_dir / BEST).model.state_dict())
            optimiser = torch.optim.Adam(model.parameters(), lr=cfg.calibration_learning_rate)
        calibrate_sigma(model, optimiser, step, since, train_set, val_set, normalisation, trained_on, meta, history,
                        device, cfg)
    if rank == 0 and shipping is not None:  # the run is done: only now is the file to ship replaced
        with replacing(shipping) as temporary:
            shutil.copyfile(run_dir / BEST, temporary)
    return run_dir / BEST if shipping is None else shipping


BEST = "best.pt"
"""The run's best checkpoint so far, in its run directory: ``model_path`` (the shipped network,
with the shipped config) is replaced by it only when the run ends, so an interrupted run leaves
it as it was."""


def final_metrics(run_dir: str | Path) -> list[str]:
    """What a finished run reached on the validation split (10 frames), from its history: the
    best checkpoint's errors, and the share within +-1 sigma once the sigma is calibrated."""
    history = read_history(Path(run_dir) / "history.json")
    trained = [h for h in history if "val_rmse_with_code" in h and "huber" in h]
    if not trained:
        return [f"no validation yet in {run_dir}/history.json"]
    best = min(trained, key=lambda h: h["val_rmse_with_code"])
    lines = [f"best checkpoint (step {best['step']}), validation errors in samples (one is 156 m): RMSE "
             f"{best['val_rmse_with_code']:.3f} where there is a code to find, {best['val_rmse']:.3f} over all, "
             f"median |error| {best['val_median_abs_error']:.3f}; {100 * best['val_within_1_sigma']:.0f} % within "
             "+-1 sigma"]
    calibrated = [h for h in history if "quantile_loss" in h]
    if calibrated:
        lines.append(f"sigma calibrated (step {calibrated[-1]['step']}): {100 * calibrated[-1]['val_within_1_sigma']:.0f} "
                     "% within +-1 sigma (68 % if honest)")
    return lines


def kept_shards(cfg: TrainConfig) -> str:
    """How many of the run's shards are made (each written whole: a rerun makes the rest)."""
    wanted = {"train": cfg.train_shards, "val": cfg.val_shards, "test": cfg.test_shards}
    made = {split: len(list((Path(cfg.data_dir) / split).glob("shard_*.npz"))) for split in wanted}
    return f"kept: {cfg.data_dir}: " + ", ".join(f"{made[k]} of {wanted[k]} {k} shards" for k in wanted)


def kept_after_interrupt(run: RunConfig, config_path: str, replace_shipped: bool = False) -> list[str]:
    """What an interrupted ``deepsync train`` leaves and how to go on from it."""
    cfg = run.training
    lines = [kept_shards(cfg)]
    last = Path(cfg.run_dir) / "last.pt"
    if last.exists():
        try:
            step = read_history(Path(cfg.run_dir) / "history.json")[-1]["step"]
        except (ValueError, IndexError, KeyError):  # cut or empty: last.pt still resumes
            step = "?"
        lines.append(f"kept: {last} (step {step} of {cfg.steps + cfg.calibration_steps}) and the best checkpoint so "
                     f"far, {Path(cfg.run_dir) / BEST}")
    try:
        shipping = destination(cfg, replace_shipped)
    except ValueError:
        shipping = None
    if shipping is not None:
        lines.append(f"{shipping} is as it was (replaced only when the run ends)")
    again = " --replace-shipped" if replace_shipped else ""
    lines.append(f"resume: deepsync train --config {config_path}{again} (it picks up where it stopped)")
    return lines


def read_history(path: Path) -> list[dict]:
    """A run's history (``history.json``; empty when there is none), or ValueError naming the file."""
    if not path.exists():
        return []
    try:
        history = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise ValueError(f"{path}: unreadable ({error}); it records the run's scores: remove it (the run then "
                         "resumes keeping its best checkpoint by score from here on) or the run directory") from None
    if not isinstance(history, list) or not all(isinstance(h, dict) for h in history):
        raise ValueError(f"{path}: not a run history (a list of records)")
    return history


def write_history(history: list[dict], run_dir: Path) -> None:
    """The history and its figure, each replaced whole (a cut file broke resuming)."""
    write_text(run_dir / "history.json", json.dumps(history, indent=1))
    with replacing(run_dir / "training_curve.png") as temporary:
        plot_history(history, temporary)


def calibrate_sigma(model: TimingNet, optimiser: torch.optim.Optimizer, step: int, since: int, train_set: Examples,
                    val_set: Examples, normalisation: Normalisation, trained_on: TrainingRange, meta: dict,
                    history: list[dict], device: torch.device, cfg: TrainConfig) -> None:
    """``model``'s sigma head alone, to the 68.3 % quantile of |error| (module docstring), from
    step ``since`` to ``since + calibration_steps``; at ``step`` (past ``since``: resumed)."""
    end = since + cfg.calibration_steps
    head = model.sigma_head()
    model.requires_grad_(False)
    head.requires_grad_(True)
    run_dir = Path(cfg.run_dir)
    resumable = {**meta, "calibrating_since_step": since}  # last.pt's: where a rerun picks up
    with tqdm(total=end, initial=step, desc="calibrating sigma", unit="step") as bar:
        while step < end:
            rng = np.random.default_rng([cfg.seed, step, 0])
            torch.manual_seed(int(rng.integers(2**62)))
            frames = int(rng.integers(cfg.min_frames, cfg.max_frames + 1))
            windows, template, target, _ = train_set.batch(rng, cfg.batch_size, frames)
            windows, template = network_inputs(windows, template, normalisation)
            model.eval()  # batch norms frozen, so the offsets stay what they were
            head.train()
            offset, log_variance = model(windows.to(device), template.to(device))
            loss = quantile_loss(log_variance, offset.detach() - target.to(device))
            progress = (step - since) / cfg.calibration_steps
            for group in optimiser.param_groups:
                group["lr"] = cfg.calibration_learning_rate * 0.5 * (1 + math.cos(math.pi * progress))
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            step += 1
            bar.update(1)
            if step % cfg.eval_every == 0 or step == end:
                scores = evaluate(model, val_set, normalisation, min(10, cfg.max_frames), device,
                                  cfg.huber_min_stacked_snr_db)
                history.append({"step": step, "quantile_loss": loss.item(),
                                **{f"val_{k}": v for k, v in scores.items()}})
                bar.set_postfix(val_within_1_sigma=f"{scores['within_1_sigma']:.3f}")
                if step == end:
                    save_checkpoint(run_dir / BEST, model, trained_on, normalisation, step=step, meta=meta)
                save_checkpoint(run_dir / "last.pt", model, trained_on, normalisation, step=step,
                                optimiser=optimiser.state_dict(), meta=resumable)
                write_history(history, run_dir)


def plot_history(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    trained = [h for h in history if "huber" in h]  # the calibration's entries have a quantile loss instead
    left.semilogy([h["step"] for h in trained], [h["huber"] for h in trained], label="train Huber (last batch)")
    left.semilogy(steps, [h["val_rmse"] for h in history], label="validation RMSE (samples, 10 frames)")
    coded = [h for h in history if "val_rmse_with_code" in h]
    left.semilogy([h["step"] for h in coded], [h["val_rmse_with_code"] for h in coded],
                  label="validation RMSE, codes to find (selects)")
    left.semilogy(steps, [h["val_median_abs_error"] for h in history], label="validation median |error|")
    left.set_xlabel("step")
    left.legend(fontsize=8)
    left.grid(True, which="both", alpha=0.3)
    right.plot(steps, [h["val_within_1_sigma"] for h in history])
    low, high = SIGMA_CALIBRATION_BAND
    right.axhspan(low, high, color="green", alpha=0.15, label=f"calibrated ({100 * low:.0f}-{100 * high:.0f} %)")
    if any("quantile_loss" in h for h in history):
        since = max((h["step"] for h in trained), default=steps[0])
        for axis in (left, right):
            axis.axvline(since, color="grey", linestyle=":", label="the sigma head calibrated from here")
    right.set_xlabel("step")
    right.set_ylabel("validation errors within 1 sigma")
    right.legend()
    right.grid(True, alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120, format="png")
    plt.close(figure)
