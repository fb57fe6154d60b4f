"""The timing side by side's statistics (``deepsync.eval.timing``), on errors made up for them."""

import numpy as np

from deepsync.eval.timing import (
    by_coarse_error,
    by_snr,
    error_stats,
    headline,
    headline_table,
    run_estimators,
    side_by_side,
    stats_table,
    time_by_frame,
)
from deepsync.timing.registry import ESTIMATORS, Estimator, Input
from deepsync.training.dataset import DatasetConfig, frame_delay_key, frame_key, make_shard


def _results(errors: np.ndarray) -> dict[str, np.ndarray]:
    results = {f"{name}_{kind}": errors.copy() if kind == "error" else np.full(errors.size, 0.5)
               for name in side_by_side(with_frame=False) for kind in ("error", "sigma")}
    results["crlb"] = np.full(errors.size, 0.1)
    return results


def test_error_stats_count_outliers_beyond_a_sample_and_errors_within_sigma():
    stats = error_stats(np.array([0.1, -0.2, 0.3, 2.0, -4.0]), np.full(5, 0.25))
    assert stats["n"] == 5 and stats["median"] == 0.3
    assert stats["outliers"] == 2 / 5 and stats["within_1_sigma"] == 2 / 5
    assert np.isclose(stats["rmse"], np.sqrt(np.mean(np.array([0.1, 0.2, 0.3, 2.0, 4.0]) ** 2)))


def test_the_share_within_sigma_comes_with_an_interval_that_narrows_with_the_examples():
    few = error_stats(np.array([0.1, -0.2, 0.3, 2.0, -4.0]), np.full(5, 0.25))
    low, high = few["within_1_sigma_ci"]
    assert low < 0.4 < high and high - low > 0.5  # 2 of 5 says little
    errors = np.random.default_rng(5).normal(size=4000)
    many = error_stats(errors, np.ones(errors.size))
    low, high = many["within_1_sigma_ci"]
    assert low < 0.6827 < high and high - low < 0.03


def test_the_calibration_verdict_tells_a_sigma_too_small_or_too_large_from_an_honest_one():
    # 8 SNR bins of 400 Gaussian errors: the network's sigma honest, network_ml's half the
    # truth, ml's twice: in band, too small and too large in every bin
    rng = np.random.default_rng(6)
    snr = np.repeat(np.arange(-27.5, 10.0, 5.0), 400)
    errors = rng.normal(size=snr.size)
    results = _results(errors)
    results["network_ml_sigma"] = np.full(snr.size, 0.5)
    results["ml_sigma"] = np.full(snr.size, 2.0)
    results["network_sigma"] = np.ones(snr.size)
    data = {"snr_db": snr, "coarse_error": np.zeros(snr.size)}
    everything = np.ones(snr.size, dtype=bool)
    rows = by_snr(data, results, everything)
    verdicts = headline(data, {"frames": {"10": {"by_snr": rows, "los_by_snr": rows}}})["within_1_sigma_snr_bins"]
    assert verdicts["network"] == {"bins": 8, "in_band": 8, "sigma_too_small": 0, "sigma_too_large": 0}
    assert verdicts["network_ml"]["sigma_too_small"] == 8 and verdicts["ml"]["sigma_too_large"] == 8


def test_the_coarse_error_breakdown_puts_each_example_in_the_bin_of_its_distance_either_way():
    coarse = np.array([0, 1, -2, 3, -5, 6, -8, 8])
    errors = np.where(np.abs(coarse) >= 6, 3.0, 0.05)  # only the lock's far edge goes wrong
    table = by_coarse_error({"coarse_error": coarse}, _results(errors))
    assert list(table) == ["0-2", "3-5", "6-8"]
    assert [table[b]["ml"]["n"] for b in table] == [3, 2, 3]
    assert table["0-2"]["network"]["outliers"] == 0 and table["3-5"]["ml"]["median"] == 0.05
    assert table["6-8"]["network_ml"]["outliers"] == 1 and table["6-8"]["crlb_median"] == 0.1


def test_the_coarse_error_bins_reach_as_far_as_the_data_does():
    coarse = np.array([0, 4, 9, 10])
    table = by_coarse_error({"coarse_error": coarse}, _results(np.zeros(coarse.size)))
    assert list(table) == ["0-2", "3-5", "6-8", "9-10"]
    assert table["6-8"]["ml"] == {"n": 0} and table["9-10"]["ml"]["n"] == 2


def test_without_a_network_the_classical_estimators_run_and_the_networks_rows_stay_empty():
    """Windows the network does not take (``benchmarks/timing/coarse_bound.py``'s wider ones) are
    still timed by every classical estimator, near the true offset for a clean code."""
    rng = np.random.default_rng(4)
    template = np.convolve(rng.normal(size=60), np.ones(4) / 4, mode="same")
    margin, offsets = 12, np.array([-3.0, 0.0, 5.0])
    windows = np.zeros((3, 4, template.size + 2 * margin))
    for k, offset in enumerate(offsets):
        windows[k, :, margin + int(offset) : margin + int(offset) + template.size] = template
    windows += 0.01 * rng.normal(size=windows.shape)
    data = {"windows": windows, "template": np.tile(template, (3, 1)), "offset": offsets}
    results = run_estimators(data, 4, None, progress=False)
    assert np.all(np.isnan(results["network_error"])) and np.all(np.isnan(results["network_ml_error"]))
    for name in (e.name for e in ESTIMATORS.values() if e.input is Input.WINDOWS):
        assert np.all(np.abs(results[f"{name}_error"]) < 0.1), name


def test_ml_frame_times_the_examples_of_a_split_that_keeps_their_mean_frames_at_the_label():
    """``frame_means``: each example's mean frame of F stacked frames, its sample 0 at the
    window's coarse code start. Through the timing stage, ``ml_frame`` finds the label on
    strong clean cells and pairs at every F kept (a frame turned the wrong way, or a pair's
    coefficients in the wrong order, would put it samples off), and the side by side scores it
    only at the F the split keeps."""
    config = DatasetConfig(max_frames=6, re_power_dbm=(-85.0, -75.0), examples_per_shard=8, channel="clean",
                           cosited_share=0.5, cosited_power_db=(-3.0, 0.0), frame_means=(3, 6))
    shard = make_shard(config, "test", 0)
    assert shard[frame_key(3)].shape == shard[frame_key(6)].shape == (8, 19200)
    assert shard[frame_delay_key(3)].shape == (8,)
    strong = shard["snr_db"] > -25
    assert strong.sum() >= 4 and np.any(shard["cosited_pci"][strong] >= 0)
    for frames in (3, 6):
        timed = np.array(time_by_frame(shard, frames, Estimator.named("ml_frame"), progress=False))
        errors = timed[:, 0] - shard["offset"]
        assert np.all(np.abs(errors[strong]) < np.maximum(4 * timed[strong, 1], 0.1)), (errors, timed[:, 1])
    assert "ml_frame_error" in run_estimators(shard, 6, None, progress=False)
    assert "ml_frame_error" not in run_estimators(shard, 5, None, progress=False)


def test_evaluate_timing_without_examples_says_what_to_run_first_and_exits_2(tmp_path, capsys):
    from deepsync.cli import main

    assert main(["evaluate-timing", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert "deepsync make-dataset --config config/timing/timing_net.yaml" in error and "minutes" in error
    assert "--bag" in error  # what can be scored without them


def test_the_headline_and_the_statistics_print_as_tables_without_none_or_nan():
    rng = np.random.default_rng(3)
    snr = np.repeat(np.arange(-27.5, 10, 5.0), 30)
    results = _results(rng.normal(scale=0.4, size=snr.size))
    results["ml_error"][:] = np.nan  # an estimator that timed nothing
    data = {"snr_db": snr, "coarse_error": np.zeros(snr.size)}
    everything = np.ones(snr.size, dtype=bool)
    rows = by_snr(data, results, everything)
    lines = headline_table(headline(data, {"frames": {"10": {"by_snr": rows, "los_by_snr": rows}}}))
    stats = stats_table({name: error_stats(results[f"{name}_error"][np.isfinite(results[f"{name}_error"])])
                         for name in side_by_side(with_frame=False)})
    text = "\n".join([*lines, *stats])
    assert not any(word in text for word in ("None", "nan", "{", "["))
    assert len(lines) == 2 + len(side_by_side(with_frame=False)) and "never" in text and "no cell timed" in text
    network = next(line for line in lines if line.startswith("network "))
    # RMSE 0.4 against a bound of 0.1 in every bin, up to the last (+5..+10 dB); errors beyond a sample: ~1 %
    assert network.split()[1:4] == ["+10", "dB", "never"], network


def test_evaluate_timing_writes_the_json_and_the_figure_it_promises_and_prints_tables(tmp_path, capsys):
    """On a split of one small shard (12 frames, as the shipped network takes them)."""
    import pytest

    pytest.importorskip("torch", reason="the side by side runs the network")
    from deepsync.cli import main
    from deepsync.training.dataset import _write_shard

    _write_shard(DatasetConfig(max_frames=12, re_power_dbm=(-90.0, -75.0), examples_per_shard=12), tmp_path / "data",
                 "test", 0)
    out = tmp_path / "out"
    assert main(["evaluate-timing", "--data", str(tmp_path / "data"), "--frames", "10", "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert (out / "timing.json").stat().st_size > 0 and (out / "timing.png").read_bytes()[:4] == b"\x89PNG"
    assert "RMSE > 2 CRLB" in printed and "within 1 sigma" in printed
    assert not any(word in printed for word in ("None", "nan", "{'"))
