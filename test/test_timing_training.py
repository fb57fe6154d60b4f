"""Training data and training of the timing network: labels that are right, shards that are
reproducible and resumable, a seconds-long training that resumes where it stopped."""

import json
from pathlib import Path

import numpy as np
import pytest

from deepsync.configio import ConfigError
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.timing.estimators import estimate_ml, noise_psd
from deepsync.training.dataset import (
    CONFIG_KEY,
    LOS_PROFILES,
    PROFILES,
    SHARD_KEYS,
    Channel,
    DatasetConfig,
    generate,
    load_split,
    make_shard,
    shard_path,
    simulate_scene,
)

TINY = DatasetConfig(max_frames=4, examples_per_shard=3)


def test_labels_are_the_true_code_start_that_ml_finds_in_clean_line_of_sight():
    """Where ML is unbiased (LOS, strong), it must agree with the label: a label off by a
    sample, a sign or a clock term shows here."""
    config = DatasetConfig(max_frames=6, re_power_dbm=(-85.0, -75.0))
    frontend = FrontendConfig()
    templates = SyncTemplates(frontend)
    rng = np.random.default_rng(3)
    checked = []
    while len(checked) < 4:
        for example in simulate_scene(config, frontend, rng, templates):
            if PROFILES[example.profile] in LOS_PROFILES and example.snr_db > -8 and example.delay_spread_ns < 100:
                estimate = estimate_ml(example.windows, example.template, config.window_margin,
                                       noise_psd(example.windows))
                checked.append(estimate.offset - example.offset)
                assert abs(example.offset) <= config.max_coarse_error + 1
    assert np.max(np.abs(checked)) < 0.1, checked


def test_a_shard_is_the_same_whoever_makes_it_and_splits_differ():
    first, again = make_shard(TINY, "val", 0), make_shard(TINY, "val", 0)
    assert set(first) == {*SHARD_KEYS, "dataset_config"}
    for key in SHARD_KEYS:
        np.testing.assert_array_equal(first[key], again[key])
    assert first["windows"].shape == (3, 4, 296) and first["template"].shape == (3, 276)
    assert not np.array_equal(first["offset"], make_shard(TINY, "test", 0)["offset"])


def test_generation_resumes_without_remaking_shards(tmp_path):
    made = generate(tmp_path, {"val": 2}, TINY)
    assert made == 6
    path = shard_path(tmp_path, "val", 0)
    before = path.stat().st_mtime_ns
    path_1 = shard_path(tmp_path, "val", 1)
    path_1.unlink()  # as if interrupted before it was written
    assert generate(tmp_path, {"val": 2}, TINY) == 3
    assert path.stat().st_mtime_ns == before and path_1.exists()
    assert len(load_split(tmp_path, "val")["offset"]) == 6
    assert len(load_split(tmp_path, "val", 1)["offset"]) == 3  # a run loads the shards it counts (and bounds)
    assert not list((tmp_path / "val").glob("*.tmp")) and not list((tmp_path / "val").glob(".*.partial"))
    with pytest.raises(ValueError, match="another dataset config .*max_frames 4 -> 5"):
        generate(tmp_path, {"val": 2}, DatasetConfig(max_frames=5, examples_per_shard=3))


def test_missing_or_foreign_shards_are_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="no shards"):
        load_split(tmp_path, "train")
    (tmp_path / "train").mkdir()
    np.savez(tmp_path / "train" / "shard_00000.npz", windows=np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match="missing template"):
        load_split(tmp_path, "train")


def test_a_clean_channel_is_one_path_that_ml_times_at_its_sigma():
    """``channel: clean`` (the estimators' reference case): every cell one path, no spread, and
    ML's error on a strong code as small as its sigma says; a fading or multipath tap left in
    would show as a bias of tenths of a sample."""
    config = DatasetConfig(max_frames=10, re_power_dbm=(-80.0, -70.0), examples_per_shard=16, channel="clean")
    assert config.channel is Channel.CLEAN
    shard = make_shard(config, "test", 0)
    assert {PROFILES[k] for k in shard["profile"]} == {"clean"} and not np.any(shard["delay_spread_ns"])
    strong = shard["snr_db"] > -16  # above ML's threshold with 10 frames
    assert strong.sum() >= 3
    for windows, template, offset in zip(shard["windows"][strong], shard["template"][strong], shard["offset"][strong]):
        w = windows.astype(np.float64)
        estimate = estimate_ml(w, template.astype(np.float64), config.window_margin, noise_psd(w))
        assert abs(estimate.offset - offset) < max(4 * estimate.std, 0.03), (estimate, offset)


def test_a_cosited_pair_is_one_example_whose_fitted_model_ml_times_and_explains_more_than_either_code():
    """The pair's template must be the fitted sum of both sectors (fitted at the code, with the
    pair's coefficient order): ML with it finds the label on a strong clean pair, and it
    explains more of the stacked code window than either sector's own template (1.7-10x here)."""
    config = DatasetConfig(max_frames=10, re_power_dbm=(-85.0, -75.0), channel="clean", cosited_share=1.0,
                           cosited_power_db=(-3.0, 0.0))
    frontend = FrontendConfig()
    templates = SyncTemplates(frontend)
    rng = np.random.default_rng(5)
    pairs = 0
    while pairs < 4:
        examples = simulate_scene(config, frontend, rng, templates)
        paired = [e for e in examples if e.cosited_pci >= 0]
        assert len(paired) <= 1 and paired == examples[: len(paired)]  # the target's, one for both sectors
        for example in paired:
            pairs += 1
            assert example.cosited_pci // 3 == example.pci // 3 and example.cosited_pci != example.pci
            w = example.windows.astype(np.float64)
            estimate = estimate_ml(w, example.template.astype(np.float64), config.window_margin, noise_psd(w))
            assert abs(estimate.offset - example.offset) < max(4 * estimate.std, 0.05), (estimate, example.offset)
            stacked = w.mean(axis=0)
            start = config.window_margin + round(example.offset)

            def explained(template: np.ndarray) -> float:  # share of the stacked code window's energy
                code = stacked[start : start + len(template)] - stacked[start : start + len(template)].mean()
                t = template - template.mean()
                return float((code @ t) ** 2 / (t @ t) / (code @ code))

            alone = max(explained(templates.template(pci)) for pci in (example.pci, example.cosited_pci))
            assert explained(example.template) > 1.5 * alone, example


def test_shards_made_before_a_config_field_existed_still_resume(tmp_path):
    """A shard's recorded config without a field added since (here ``channel`` and the pairs')
    was made with that field's default: resuming accepts it, loading fills a key added since
    with what such shards held, and another value of the field is refused."""
    generate(tmp_path, {"val": 1}, TINY)
    path = shard_path(tmp_path, "val", 0)
    with np.load(path) as shard:
        arrays = dict(shard)
    recorded = json.loads(str(arrays[CONFIG_KEY]))
    for added in ("channel", "cosited_share", "cosited_power_db"):
        del recorded[added]
    arrays[CONFIG_KEY] = np.array(json.dumps(recorded))
    np.savez(path, **arrays)
    assert generate(tmp_path, {"val": 1}, TINY) == 0
    del arrays["cosited_pci"], arrays["site_coefficients"]  # nor keys added since: those shards held no pairs
    np.savez(path, **arrays)
    loaded = load_split(tmp_path, "val")
    np.testing.assert_array_equal(loaded["cosited_pci"], [-1, -1, -1])
    assert loaded["site_coefficients"].shape == (3, 4) and np.all(np.isnan(loaded["site_coefficients"]))
    with pytest.raises(ValueError, match="channel 'tdl' -> 'clean'"):
        generate(tmp_path, {"val": 1}, DatasetConfig(max_frames=4, examples_per_shard=3, channel=Channel.CLEAN))


@pytest.mark.parametrize("change, field", [
    (dict(channel="rayleigh"), "channel"),
    (dict(max_coarse_error=10), "max_coarse_error"),
    (dict(max_frames=1), "max_frames"),
    (dict(re_power_dbm=(-70.0, -90.0)), "re_power_dbm"),
    (dict(examples_per_shard=0), "examples_per_shard"),
    (dict(cosited_share=1.5), "cosited_share"),
    (dict(cosited_power_db=(0.0, -12.0)), "cosited_power_db"),
    (dict(max_frames=4, frame_means=(2, 6)), "frame_means"),
    (dict(frame_means=(10, 5)), "frame_means"),
])
def test_a_dataset_config_that_cannot_be_names_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        DatasetConfig(**change)


# -- training ----------------------------------------------------------------------------------

torch = pytest.importorskip("torch", reason="torch is not installed (scripts/setup.sh installs the CPU wheel)")


def run_yaml(tmp_path, steps: int, model: dict | None = None, dataset: dict | None = None, **training) -> str:
    import yaml

    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({
        "dataset": {"max_frames": 4, "examples_per_shard": 8, **(dataset or {})},
        "model": {"channels": [4, 8, 8], "heads": 2, "hidden": [16, 8], **(model or {})},
        "training": {"data_dir": str(tmp_path / "data"), "train_shards": 2, "val_shards": 1, "test_shards": 1,
                     "run_dir": str(tmp_path / "run"), "model_path": str(tmp_path / "net.pt"), "steps": steps,
                     "batch_size": 8, "eval_every": 5, "max_frames": 4, "min_frames": 2, "warmup_steps": 2,
                     "workers": 1, "calibration_steps": 0, **training},
    }))
    return str(path)


def test_a_short_training_writes_a_checkpoint_the_stage_loads_and_resumes(tmp_path):
    from deepsync.timing.checkpoint import load_checkpoint
    from deepsync.training.train import load_run_config, train

    config = run_yaml(tmp_path, steps=10)
    path = train(load_run_config(config), config)
    checkpoint = load_checkpoint(path)
    assert checkpoint.training_range.max_frames == 4 and checkpoint.normalisation.window_scale > 0
    assert not checkpoint.training_range.cosited_pairs  # its data held none: the stage times pairs by ML
    assert set(checkpoint.meta) == {"config", "run", "examples", "normalisation"}  # how it was made
    assert checkpoint.meta["examples"] > 0 and json.loads(checkpoint.meta["run"])["model"]["fusion"] == "cross_attention"
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["step"] for h in history] == [5, 10]
    assert (tmp_path / "run" / "training_curve.png").stat().st_size > 1000

    longer = run_yaml(tmp_path, steps=15)  # the same run, asked for more: resumes at step 10
    train(load_run_config(longer), longer)
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["step"] for h in history] == [5, 10, 15]
    assert load_checkpoint(tmp_path / "run" / "last.pt").step == 15

    import yaml

    other = run_yaml(tmp_path, steps=20)  # another model in the same run directory: refused, not mixed
    content = yaml.safe_load(Path(other).read_text())
    content["model"]["hidden"] = [32, 8]
    Path(other).write_text(yaml.safe_dump(content))
    with pytest.raises(ValueError, match="another model config"):
        train(load_run_config(other), other)


def test_a_run_on_data_with_pairs_says_so_and_its_network_times_pairs(tmp_path):
    from deepsync.timing.network import NetworkEstimator
    from deepsync.training.train import load_run_config, train
    from deepsync.types import SyncWindow

    config = run_yaml(tmp_path, steps=2, dataset={"cosited_share": 1.0})
    network = NetworkEstimator(train(load_run_config(config), config))
    assert network.range.cosited_pairs
    shard = load_split(tmp_path / "data", "train")
    assert np.any(shard["cosited_pci"] >= 0)
    pair = SyncWindow(0, 5, 5000, shard["windows"][0], 12.0, 0.0, cosited_pci=6, site_coefficients=(1.0, 1.0, 0.5, 0.0))
    assert network.refusal(pair, 1.92e6, 276) is None


@pytest.mark.parametrize("stop", [5, 15], ids=["training", "calibrating the sigma"])
def test_a_resumed_run_takes_the_same_path_as_an_uninterrupted_one(tmp_path, monkeypatch, stop):
    from deepsync.timing.checkpoint import load_checkpoint
    from deepsync.training import train as training
    from deepsync.training.train import load_run_config, train

    straight = run_yaml(tmp_path, steps=10, calibration_steps=10, run_dir=str(tmp_path / "straight"))
    train(load_run_config(straight), straight)
    interrupted = run_yaml(tmp_path, steps=10, calibration_steps=10, run_dir=str(tmp_path / "resumed"))
    plot = training.plot_history

    def ctrl_c_after_the_stop(history, path):
        plot(history, path)
        if history[-1]["step"] == stop:
            raise KeyboardInterrupt

    monkeypatch.setattr(training, "plot_history", ctrl_c_after_the_stop)
    with pytest.raises(KeyboardInterrupt):
        train(load_run_config(interrupted), interrupted)
    monkeypatch.setattr(training, "plot_history", plot)
    train(load_run_config(interrupted), interrupted)
    a = load_checkpoint(tmp_path / "straight" / "last.pt").model.state_dict()
    b = load_checkpoint(tmp_path / "resumed" / "last.pt").model.state_dict()
    for name in a:
        torch.testing.assert_close(a[name], b[name])


def test_the_quantile_loss_is_least_where_sigma_holds_68_percent_of_the_errors():
    """On errors with wrong-lobe tails (a narrow core and a few far ones), the sigma the
    Gaussian NLL picks (their RMS) holds nearly all of them; the pinball loss picks one
    that holds a Gaussian's 68.3 %."""
    from deepsync.training.train import SIGMA_QUANTILE, quantile_loss

    rng = np.random.default_rng(3)
    errors = np.where(rng.random(20000) < 0.8, rng.normal(0, 0.2, 20000), rng.uniform(-8, 8, 20000))
    sigmas = np.geomspace(0.01, 10, 600)
    losses = [float(quantile_loss(torch.full((errors.size,), 2 * np.log(s)), torch.from_numpy(errors)))
              for s in sigmas]
    best = sigmas[int(np.argmin(losses))]
    assert abs(np.mean(np.abs(errors) <= best) - SIGMA_QUANTILE) < 0.01
    assert np.mean(np.abs(errors) <= np.sqrt(np.mean(errors**2))) > 0.85


def test_calibrating_the_sigma_moves_no_offset_and_a_longer_run_is_refused(tmp_path):
    from deepsync.timing.checkpoint import load_checkpoint
    from deepsync.timing.inputs import network_inputs
    from deepsync.training.train import load_run_config, train

    shipped = {"fusion": "correlation", "head": "soft_argmax"}  # its sigma head: the dense layers, with dropout
    plain = run_yaml(tmp_path, steps=10, model=shipped, run_dir=str(tmp_path / "plain"),
                     model_path=str(tmp_path / "plain.pt"))
    train(load_run_config(plain), plain)
    config = run_yaml(tmp_path, steps=10, model=shipped, calibration_steps=10)
    train(load_run_config(config), config)
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["step"] for h in history] == [5, 10, 15, 20] and "quantile_loss" in history[-1]
    before, after = load_checkpoint(tmp_path / "plain.pt"), load_checkpoint(tmp_path / "net.pt")
    assert after.step == 20 and "calibrating_since_step" not in after.meta
    assert load_checkpoint(tmp_path / "run" / "last.pt").meta["calibrating_since_step"] == 10
    data = load_split(tmp_path / "data", "val")
    windows, template = network_inputs(torch.from_numpy(data["windows"]), torch.from_numpy(data["template"]),
                                       after.normalisation)
    with torch.no_grad():
        (offset_before, log_variance_before), (offset_after, log_variance_after) = (
            before.model(windows, template), after.model(windows, template))
    torch.testing.assert_close(offset_after, offset_before, rtol=0, atol=0)
    assert not torch.equal(log_variance_after, log_variance_before)

    train(load_run_config(config), config)  # finished: a rerun does nothing
    assert load_checkpoint(tmp_path / "run" / "last.pt").step == 20
    longer = run_yaml(tmp_path, steps=15, model=shipped, calibration_steps=10)
    with pytest.raises(ValueError, match="calibrating its sigma since step 10"):
        train(load_run_config(longer), longer)


def test_a_run_config_that_does_not_fit_names_the_field(tmp_path):
    import yaml

    from deepsync.training.train import load_run_config

    path = tmp_path / "run.yaml"
    for content, message in [
        ({"training": {"max_frames": 30}}, "max_frames"),
        ({"model": {"window_length": 300}}, "window_length"),
        ({"training": {"steps": 0}}, "steps"),
        ({"training": {"calibration_steps": -1}}, "calibration_steps"),
        ({"schedule": {}}, "unknown section schedule"),
        ({"training": {"learning_rat": 1.0}}, "learning_rat"),
        ({"model": {"fusion": "sum"}}, "model: fusion must be one of cross_attention, concatenation, .*got 'sum'"),
    ]:
        path.write_text(yaml.safe_dump(content))
        with pytest.raises(ConfigError, match=message):
            load_run_config(path)
    path.write_text(yaml.safe_dump({"model": {"fusion": "correlation", "head": "soft_argmax"}}))
    model = load_run_config(path).model
    assert (model.fusion.value, model.head.value) == ("correlation", "soft_argmax")


def test_validation_picks_by_the_examples_with_a_code_and_by_all_where_none_has_one():
    """The checkpoint is chosen by ``rmse_with_code``: NaN (no example above the threshold)
    would never be the best, and no checkpoint would ever be written."""
    import torch

    from deepsync.timing.inputs import Normalisation
    from deepsync.timing.model import TimingNet, TimingNetConfig
    from deepsync.training.train import Examples, evaluate

    torch.manual_seed(0)
    model = TimingNet(TimingNetConfig())
    rng = np.random.default_rng(0)
    arrays = {"windows": rng.normal(size=(6, 4, 296)).astype(np.float32),
              "template": rng.normal(size=(6, 276)).astype(np.float32),
              "offset": np.array([0.0, 1.0, -2.0, 3.0, 0.5, -4.0]), "cosited_pci": np.full(6, -1)}
    weak = Examples({**arrays, "snr_db": np.full(6, -40.0)})
    scores = evaluate(model, weak, Normalisation(1.0), 4, torch.device("cpu"), min_stacked_snr_db=-5.0)
    assert np.isfinite(scores["rmse_with_code"]) and scores["rmse_with_code"] == scores["rmse"]
    mixed = Examples({**arrays, "snr_db": np.array([-40.0, -40.0, -40.0, 0.0, 0.0, 0.0])})
    scores = evaluate(model, mixed, Normalisation(1.0), 4, torch.device("cpu"), min_stacked_snr_db=-5.0)
    assert scores["rmse_with_code"] != scores["rmse"]


def test_an_interrupted_run_keeps_the_file_it_would_replace_and_a_cut_history_names_itself(tmp_path, monkeypatch, capsys):
    """On main SIGTERM mid-run said "nothing was written" though last.pt and the model had been
    written, the model over the file at model_path (with the shipped config, the shipped
    network); history.json was written in place, and a cut one broke resuming with an error
    naming no file."""
    from deepsync.cli import main
    from deepsync.timing.checkpoint import load_checkpoint
    from deepsync.training import train as training

    shipped = tmp_path / "net.pt"
    shipped.write_bytes(b"the network that was there")
    config = run_yaml(tmp_path, steps=10)
    plot = training.plot_history

    def interrupt_after_the_first_evaluation(history, path):
        plot(history, path)
        raise KeyboardInterrupt

    monkeypatch.setattr(training, "plot_history", interrupt_after_the_first_evaluation)
    assert main(["train", "--config", config]) == 130
    err = capsys.readouterr().err
    assert f"kept: {tmp_path / 'run' / 'last.pt'} (step 5 of 10)" in err and f"{shipped} is as it was" in err
    assert f"resume: deepsync train --config {config}" in err and "nothing was written" not in err
    assert shipped.read_bytes() == b"the network that was there"
    assert load_checkpoint(tmp_path / "run" / "best.pt").step == 5 and load_checkpoint(tmp_path / "run" / "last.pt").step == 5
    assert not list((tmp_path / "run").glob(".*.partial"))
    monkeypatch.setattr(training, "plot_history", plot)
    history = tmp_path / "run" / "history.json"
    history.write_text(history.read_text()[:20])  # as a crash mid-write left it on main
    assert main(["train", "--config", config]) == 2
    assert f"{history}: unreadable" in capsys.readouterr().err
    history.unlink()
    assert main(["train", "--config", config]) == 0
    assert load_checkpoint(shipped).step == 10


def test_a_copied_config_never_replaces_the_shipped_network_unless_asked(tmp_path, capsys):
    """A config copied from the shipped one once replaced the shipped timing_net.pt when its run
    ended. Now a run's network stays in its run directory; a config naming the shipped file is
    refused at the door unless --replace-shipped asks for it; the end prints the metrics."""
    from deepsync.cli import main
    from deepsync.timing.network import DEFAULT_CHECKPOINT

    shipped = DEFAULT_CHECKPOINT.read_bytes()
    naming = run_yaml(tmp_path, steps=5, model_path=str(DEFAULT_CHECKPOINT))
    assert main(["train", "--config", naming]) == 2
    error = capsys.readouterr().err
    assert "--replace-shipped" in error and str(tmp_path / "run" / "best.pt") in error
    assert not (tmp_path / "data").exists()  # refused before any work
    elsewhere = run_yaml(tmp_path, steps=5, model_path=str(tmp_path / "other.pt"))
    assert main(["train", "--config", elsewhere, "--replace-shipped"]) == 2
    assert "remove one of them" in capsys.readouterr().err
    plain = run_yaml(tmp_path, steps=5, model_path="")
    assert main(["train", "--config", plain]) == 0
    out = capsys.readouterr().out
    assert f"trained network: {tmp_path / 'run' / 'best.pt'}" in out
    assert "best checkpoint (step 5), validation errors in samples" in out and "RMSE" in out
    assert DEFAULT_CHECKPOINT.read_bytes() == shipped
