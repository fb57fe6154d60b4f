"""One registry of timing estimators (``deepsync.timing.registry``): every registered estimator
is taken by the timing stage, the command line, the evaluation and the ROS parameter, and one
registered in a test reaches all of them with nothing else changed."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from deepsync.cli import build_parser
from deepsync.eval.timing import run_estimators, side_by_side
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates, code_template
from deepsync.timing.estimators import estimate_parabolic
from deepsync.timing.registry import ESTIMATORS, Estimator, Input, register
from deepsync.timing.stage import TimingConfig, TimingStage
from deepsync.types import SyncWindow

PCI = 120


def _replay_args(name: str) -> list[str]:
    return ["replay", "--in", "bags/campus_route", "--out", "/nonexistent/out", "--estimator", name]


@pytest.fixture(scope="module")
def cell() -> tuple[FrontendConfig, SyncWindow, float]:
    """A clean code at a fractional offset in 8 frames of windows, with a little noise."""
    frontend = FrontendConfig()
    template = code_template(SyncTemplates(frontend), PCI)
    margin, shift = 20, 3.4
    rng = np.random.default_rng(1)
    grid = np.arange(template.size + 2 * margin)
    row = np.interp(grid - margin - shift, np.arange(template.size), template, left=0.0, right=0.0)
    windows = (row + 0.02 * np.std(template) * rng.normal(size=(8, grid.size))).astype(np.float32)
    return frontend, SyncWindow(0, PCI, 1000, windows, 10.0, 0.0), shift


@pytest.fixture
def added():
    """An estimator registered for the test only (parabolic under another name)."""
    estimator = register(Estimator("parabolic_copy", "a test's copy of parabolic", Input.WINDOWS,
                                   on_windows=lambda w, t, m, psd: estimate_parabolic(w, t, m)))
    yield estimator
    del ESTIMATORS[estimator.name]


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_every_registered_estimator_is_taken_by_the_stage_the_cli_and_the_evaluation(name, cell):
    estimator = ESTIMATORS[name]
    assert Estimator.named(name) is estimator
    assert build_parser().parse_args(_replay_args(name)).estimator == name
    assert name in side_by_side()
    if estimator.uses_network and importlib.util.find_spec("torch") is None:
        pytest.skip("the network estimators need torch")
    frontend, window, shift = cell
    timed = TimingStage(frontend, TimingConfig(estimator)).process([window])
    assert len(timed.cells) == 1 and not timed.events
    assert timed.cells[0].toa == pytest.approx(1000 + shift, abs=0.3)


def test_an_estimator_registered_in_one_place_reaches_the_stage_the_cli_and_the_evaluation(added, cell):
    frontend, window, shift = cell
    (timed,) = TimingStage(frontend, TimingConfig(Estimator.named(added.name))).process([window]).cells
    assert timed.estimator == added.name and timed.toa == pytest.approx(1000 + shift, abs=0.3)
    assert build_parser().parse_args(_replay_args(added.name)).estimator == added.name
    assert added.name in side_by_side(with_frame=False)
    data = {"windows": window.windows[None].astype(np.float64), "template": code_template(
        SyncTemplates(frontend), PCI)[None], "offset": np.array([shift])}
    results = run_estimators(data, 8, None, progress=False)
    assert abs(results[f"{added.name}_error"][0]) < 0.3


def test_an_unknown_estimator_is_an_error_naming_the_known_ones(capsys):
    with pytest.raises(ValueError) as error:
        Estimator.named("parabolic2")
    assert all(name in str(error.value) for name in ESTIMATORS)
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(_replay_args("parabolic2"))
    assert exit_.value.code == 2 and "ml_frame" in capsys.readouterr().err
    with pytest.raises(ValueError, match="must be one of"):
        TimingConfig(estimator="parabolic")  # a name is looked up by Estimator.named, never taken as is


def test_a_registration_that_would_leave_a_gap_is_refused():
    with pytest.raises(ValueError, match="registered already"):
        register(Estimator("ml", "again", Input.WINDOWS, on_windows=ESTIMATORS["ml"].on_windows))
    with pytest.raises(ValueError, match="fallback"):
        register(Estimator("frame_copy", "no fallback", Input.FRAME))
    with pytest.raises(ValueError, match="fallback"):
        register(Estimator("frame_copy", "a fallback of the frame", Input.FRAME, fallback="ml_frame"))
    with pytest.raises(ValueError, match="needs its function"):
        Estimator("windows_copy", "no function", Input.WINDOWS)
    assert "frame_copy" not in ESTIMATORS
