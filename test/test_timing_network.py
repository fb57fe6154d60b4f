"""The timing network inside the timing stage: one batch per stack, ML outside its training
range (and saying why), the shipped checkpoint, and torch kept out of everything else."""

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="torch is not installed (scripts/setup.sh installs the CPU wheel)")

from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, code_template  # noqa: E402
from deepsync.timing.checkpoint import CheckpointError, TrainingRange, load_checkpoint, save_checkpoint  # noqa: E402
from deepsync.timing.inputs import Normalisation, network_inputs  # noqa: E402
from deepsync.timing.model import TimingNet  # noqa: E402
from deepsync.timing.network import DEFAULT_CHECKPOINT  # noqa: E402
from deepsync.timing.stage import Estimator, TimingConfig, TimingStage  # noqa: E402
from deepsync.types import SyncWindow  # noqa: E402

RANGE = TrainingRange(sample_rate=1.92e6, min_frames=4, max_frames=12, min_snr_db=-40.0, max_snr_db=0.0,
                      cosited_pairs=False)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("net") / "net.pt"
    save_checkpoint(path, TimingNet().eval(), RANGE, Normalisation(1.3))
    return path


@pytest.fixture(scope="module")
def frontend():
    return FrontendConfig()


def window(pci: int, frames: int = 10, snr_db: float = 0.0, seed: int = 0, pair: int | None = None,
           length: int = 296) -> SyncWindow:
    """A code at offset +1.3 in noise (stacked SNR ``snr_db`` as the sync stage reports it)."""
    rng = np.random.default_rng(seed)
    template = code_template(SyncTemplates(FrontendConfig()), pci)
    rows = rng.normal(size=(frames, length)) * 1e-3
    rows[:, 11 : 11 + len(template)] += template / np.abs(template).max() * 1e-3
    return SyncWindow(0, pci, 5000, rows.astype(np.float32), 12.0, snr_db,
                      cosited_pci=pair, site_coefficients=None if pair is None else (1.0, 1.0, 0.0, 0.0))


def test_every_cell_of_a_stack_goes_through_one_batch_and_gets_what_it_would_alone(checkpoint, frontend):
    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(checkpoint)))
    cells = [window(pci, seed=pci) for pci in (10, 200, 301, 77)]
    together = stage.process(cells)
    assert [c.estimator for c in together.cells] == ["network"] * 4 and not together.fallbacks
    for cell, alone in zip(together.cells, cells):
        single = stage.process([alone]).cells[0]
        assert math.isclose(cell.toa, single.toa, abs_tol=1e-4) and math.isclose(cell.toa_std, single.toa_std,
                                                                                  rel_tol=1e-4)
        assert cell.toa_std > 0 and math.isfinite(cell.crlb_std) and cell.earfcn is None


def test_a_dead_or_corrupt_window_is_reported_and_changes_no_other_cell(checkpoint, frontend):
    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(checkpoint)))
    good = window(10, seed=10)
    dead = window(11)
    dead = SyncWindow(0, 11, 5000, np.full_like(dead.windows, 0.25), 12.0, 0.0)
    broken = window(12).windows.copy()
    broken[3, 40] = np.nan
    result = stage.process([dead, good, SyncWindow(0, 12, 5000, broken, 12.0, 0.0)])
    alone = stage.process([good]).cells[0]
    assert [c.pci for c in result.cells] == [10] and result.cells[0].toa == pytest.approx(alone.toa, abs=1e-5)
    assert len(result.events) == 2 and "NaN" in result.fallbacks[0][1]


def test_the_stage_feeds_the_network_what_training_fed_it(checkpoint, frontend):
    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(checkpoint)))
    cell = window(120, seed=3)
    model = load_checkpoint(checkpoint).model
    inputs = network_inputs(torch.from_numpy(cell.windows[None]),
                            torch.from_numpy(code_template(stage.templates, 120)[None].astype(np.float32)),
                            Normalisation(1.3))
    with torch.no_grad():
        offset, _ = model(*inputs)
    assert math.isclose(stage.process([cell]).cells[0].toa, 5000 + float(offset), abs_tol=1e-4)


@pytest.mark.parametrize("cell, reason", [
    (window(5, pair=6), "co-sited pair"),
    (window(5, frames=20), "20 frames"),
    (window(5, frames=3), "3 frames"),
    (window(5, snr_db=30.0), "above the training range"),
], ids=["pair", "too_many_frames", "too_few_frames", "snr"])
def test_a_cell_outside_the_training_range_is_timed_by_ml_and_says_why(checkpoint, frontend, cell, reason):
    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(checkpoint)))
    result = stage.process([cell, window(9)])
    assert sorted(c.estimator for c in result.cells) == ["ml", "network"]
    assert len(result.fallbacks) == 1 and result.fallbacks[0][0] == 5 and reason in result.fallbacks[0][1]


def test_a_checkpoint_trained_on_pairs_times_both_sectors_of_a_pair_with_their_fitted_model(frontend, tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "pairs.pt"
    save_checkpoint(path, TimingNet().eval(), dataclasses.replace(RANGE, cosited_pairs=True), Normalisation(1.3))
    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(path)))
    pair = [window(5, pair=6), dataclasses.replace(window(5, pair=6), pci=6, cosited_pci=5)]
    result = stage.process(pair)
    assert not result.fallbacks and [c.estimator for c in result.cells] == ["network", "network"]
    assert result.cells[0].toa == result.cells[1].toa  # one code, one template: one arrival
    lone = stage.process([window(5)]).cells[0]
    assert lone.toa != result.cells[0].toa  # the pair's model, not sector 5's own template, went in


def test_a_bad_or_missing_checkpoint_fails_at_construction_and_keeps_the_running_stage(checkpoint, frontend, tmp_path):
    with pytest.raises(CheckpointError, match="no such file"):
        TimingStage(frontend, TimingConfig(estimator=Estimator.named("network"), checkpoint=str(tmp_path / "none.pt")))
    running = TimingStage(frontend)
    with pytest.raises(ValueError, match="none.pt"):
        running.with_config(TimingConfig(estimator=Estimator.named("network"), checkpoint=str(tmp_path / "none.pt")))
    assert running.config.estimator is Estimator.named("ml_frame")
    parabolic = running.with_config(TimingConfig(estimator=Estimator.named("parabolic")))
    assert parabolic.templates is running.templates  # nothing to load or build
    assert running.config.estimator is Estimator.named("ml_frame")  # the running stage is never changed
    switched = running.with_config(TimingConfig(estimator=Estimator.named("network"), checkpoint=str(checkpoint)))
    assert switched.network is not None and switched.templates is running.templates and running.network is None
    same = switched.with_config(TimingConfig(estimator=Estimator.named("network_ml"), checkpoint=str(checkpoint)))
    assert same.network is switched.network and switched.config.estimator is Estimator.named("network")  # not reloaded
    back = switched.with_config(TimingConfig())
    assert back.network is None and back.config.estimator is Estimator.named("ml_frame") and switched.network is not None


def test_the_shipped_checkpoint_times_simulated_cells_as_its_evaluation_says(frontend):
    """Strong simulated cells (their own channels, other cells around): the network and
    network_ml within a fraction of a sample (the paper's layout, shipped before the ablation,
    missed by 0.38 samples), and saying so."""
    from deepsync.training.dataset import DatasetConfig, make_shard

    assert DEFAULT_CHECKPOINT.is_file(), "the trained network must ship with deepsync"
    loaded = load_checkpoint(DEFAULT_CHECKPOINT)
    assert loaded.training_range.sample_rate == frontend.adc_rate_hz and loaded.optimiser is None
    shard = make_shard(DatasetConfig(re_power_dbm=(-85.0, -75.0), examples_per_shard=12), "test", 99)
    strong = shard["snr_db"] > -15
    cells = [SyncWindow(0, int(pci), 1000, w[:10], 10.0, -30.0) for pci, w in zip(shard["pci"], shard["windows"])]
    errors = {}
    for estimator in (Estimator.named("network"), Estimator.named("network_ml")):
        # every example, those below what the sync stage would report included (min_snr_db off)
        timed = TimingStage(frontend, TimingConfig(estimator=estimator, min_snr_db=-60.0)).process(cells).cells
        assert [c.estimator for c in timed] == [estimator.name] * len(cells)
        error = np.array([c.toa - 1000 for c in timed]) - shard["offset"]
        errors[estimator] = np.abs(error[strong])
        assert np.mean(np.abs(error) <= 3 * np.array([c.toa_std for c in timed])) >= 0.75
    assert np.median(errors[Estimator.named("network")]) < 0.3 and np.median(errors[Estimator.named("network_ml")]) < 0.3


def test_nothing_but_the_network_imports_torch():
    code = ("import sys, deepsync.pipeline, deepsync.replay, deepsync.timing.stage\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_without_torch_a_network_estimator_is_refused_with_the_cpu_wheel_to_install():
    """A robot without torch asks for estimator network: one ValueError with the pip command of
    the CPU wheel (torch from PyPI would pull GBs of CUDA), the classical estimators unaffected.
    An import hook makes torch absent, as on a machine without it."""
    code = ("import sys\n"
            "class NoTorch:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.partition('.')[0] == 'torch':\n"
            "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
            "sys.meta_path.insert(0, NoTorch())\n"
            "from deepsync.frontend.config import FrontendConfig\n"
            "from deepsync.timing.stage import Estimator, TimingConfig, TimingStage\n"
            "TimingStage(FrontendConfig(), TimingConfig(estimator=Estimator.named('ml')))\n"
            "try:\n"
            "    TimingStage(FrontendConfig(), TimingConfig(estimator=Estimator.named('network')))\n"
            "except ValueError as error:\n"
            "    print(error)\n")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.startswith("the network estimator needs torch: pip install -c constraints.txt torch --index-url "
                          "https://download.pytorch.org/whl/cpu"), out
    assert "classical estimator" in out


def test_the_onnx_export_computes_what_torch_computes(checkpoint, tmp_path):
    pytest.importorskip("onnxruntime", reason="onnxruntime is not installed (the onnx extra)")
    import onnx

    from deepsync.timing.export import check_onnx, export_onnx

    loaded = load_checkpoint(checkpoint)
    path = export_onnx(loaded, tmp_path / "out" / "net.onnx")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["net.onnx"]  # on main a stray net.onnx.data too
    assert check_onnx(path, loaded, trials=4) < 1e-4
    metadata = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert float(metadata["window_scale"]) == 1.3 and metadata["training_range.max_frames"] == "12"


def test_network_ml_times_inside_the_networks_interval_with_mls_precision(checkpoint, frontend):
    """An untrained network is unsure (a wide interval): ML then finds the code anyway, and its
    sigma carries the multipath floor."""
    from deepsync.timing.registry import MULTIPATH_FLOOR_SAMPLES

    stage = TimingStage(frontend, TimingConfig(estimator=Estimator.named("network_ml"), checkpoint=str(checkpoint)))
    cell = stage.process([window(42, snr_db=-5.0, seed=1)]).cells[0]
    assert cell.estimator == "network_ml"
    assert abs(cell.toa - 5001.0) < 0.05 and cell.toa_std >= MULTIPATH_FLOOR_SAMPLES
