"""Timing-network checkpoints: round trip, and every way a file can be wrong refused by name."""

import dataclasses
import pickle

import pytest

torch = pytest.importorskip("torch", reason="torch is not installed (scripts/setup.sh installs the CPU wheel)")

from deepsync.timing.checkpoint import (  # noqa: E402
    CheckpointError,
    TrainingRange,
    load_checkpoint,
    save_checkpoint,
)
from deepsync.timing.inputs import Normalisation  # noqa: E402
from deepsync.timing.model import Fusion, Head, TimingNet, TimingNetConfig  # noqa: E402

RANGE = TrainingRange(sample_rate=1.92e6, min_frames=5, max_frames=40, min_snr_db=-30.0, max_snr_db=10.0,
                      cosited_pairs=True)
SCALE = Normalisation(window_scale=1.7)


def trained_looking(config: TimingNetConfig | None = None) -> TimingNet:
    torch.manual_seed(1)
    model = TimingNet(config)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.1)  # not the initial weights
    return model.eval()


@pytest.mark.parametrize("config", [
    TimingNetConfig(channels=(8, 16, 16), heads=2),
    TimingNetConfig(fusion=Fusion.CORRELATION, head=Head.SOFT_ARGMAX),
], ids=["paper", "correlation+soft_argmax"])
def test_a_checkpoint_gives_back_the_same_network(tmp_path, config):
    model = trained_looking(config)
    optimiser = torch.optim.Adam(model.parameters())
    path = tmp_path / "net.pt"
    save_checkpoint(path, model, RANGE, SCALE, step=123, optimiser=optimiser.state_dict(), meta={"seed": 7})
    loaded = load_checkpoint(path)
    assert loaded.model.config == model.config and loaded.training_range == RANGE
    assert loaded.normalisation == SCALE
    assert (loaded.step, loaded.meta) == (123, {"seed": 7})
    assert not loaded.model.training
    windows, template = torch.randn(3, 10, 296), torch.randn(3, 276)
    with torch.no_grad():
        torch.testing.assert_close(loaded.model(windows, template), model(windows, template), rtol=0, atol=0)
    torch.optim.Adam(loaded.model.parameters()).load_state_dict(loaded.optimiser)  # resumable


def test_a_file_that_would_run_code_is_refused_without_running_it(tmp_path, capsys):
    class Payload:
        def __reduce__(self):
            return (print, ("this must never be printed",))

    path = tmp_path / "evil.pt"
    torch.save({"format": "deepsync-timing-net", "trap": Payload()}, path)
    with pytest.raises(CheckpointError, match="weights_only"):
        load_checkpoint(path)
    assert "never be printed" not in capsys.readouterr().out


@pytest.mark.parametrize("tamper, message", [
    (lambda p: p.update(format="something-else"), "format"),
    (lambda p: p.update(version=99), "version"),
    (lambda p: p["config"].update(channels=[8, 16, 64]), "weight"),
    (lambda p: p["config"].update(heads=3), "heads"),
    (lambda p: p["config"].update(colour="blue"), "unknown: colour"),
    (lambda p: p["config"].update(fusion="sum"), "fusion"),
    (lambda p: p["config"].update(head="dense", fusion="correlation"), "weights do not match"),
    (lambda p: p["training_range"].pop("max_frames"), "missing: max_frames"),
    (lambda p: p["state_dict"].pop("offset.bias"), "missing: offset.bias"),
    (lambda p: p["state_dict"]["offset.bias"].fill_(float("nan")), "NaN"),
    (lambda p: p.update(step="many"), "step"),
    (lambda p: p["normalisation"].update(window_scale=-1.0), "window_scale"),
    (lambda p: p.pop("normalisation"), "normalisation"),
    # on main the network was built before its sizes were judged: 3.3 GB, and a 14 GB traceback
    (lambda p: p["config"].update(hidden=[2e6, 32]), "hidden must be an integer, got 2000000.0"),
    (lambda p: p["config"].update(hidden=[10**7, 1000]), "hidden must be within"),
    (lambda p: p["config"].update(hidden=[60000, 32]), "16,000,000 allowed"),
    (lambda p: p["config"].update(window_length=10**9), "window_length must be within"),
], ids=["format", "version", "shapes", "config_value", "config_field", "fusion_name", "fusion_other", "range_field", "weight_missing",
        "weight_nan", "step_type", "normalisation_value", "normalisation_missing", "hidden_2e6", "hidden_1e7",
        "too_many_weights", "window_1e9"])
def test_a_mismatched_or_tampered_checkpoint_is_refused_by_name(tmp_path, tamper, message):
    path = tmp_path / "net.pt"
    save_checkpoint(path, trained_looking(), RANGE, SCALE)
    payload = torch.load(path, weights_only=True)
    tamper(payload)
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")  # torch's note on the plain pickle
@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", pickle.dumps([1, 2, 3]),
                                     b"rosbag2_bagfile_information:\n  version: 9\n"],
                         ids=["empty", "text", "plain_pickle", "yaml"])  # yaml: torch's loader raised IndexError
def test_what_is_not_a_checkpoint_says_so(tmp_path, content):
    path = tmp_path / "net.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


def test_a_missing_file_says_so(tmp_path):
    with pytest.raises(CheckpointError, match="no such file"):
        load_checkpoint(tmp_path / "absent.pt")


def test_a_truncated_checkpoint_is_refused(tmp_path):
    path = tmp_path / "net.pt"
    save_checkpoint(path, trained_looking(), RANGE, SCALE)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="not a loadable checkpoint"):
        load_checkpoint(path)


@pytest.mark.parametrize("change, field", [
    (dict(min_frames=0), "min_frames"),
    (dict(min_frames=50), "max_frames"),
    (dict(min_snr_db=20.0), "min_snr_db"),
    (dict(sample_rate=0.0), "sample_rate"),
])
def test_a_training_range_that_cannot_be_names_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(RANGE, **change)
