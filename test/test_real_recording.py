"""The envelope-domain cell search on a real over-the-air LTE recording, against a coherent search.

|x|^2 of the RTL-SDR's complex baseband is the envelope a square-law detector would give for this
one carrier (real multipath, load and receiver clock). The coherent (complex-domain) PSS/SSS
search of ``deepsync.testing.coherent`` on the same samples is the reference. The recording goes
through the pipeline as a source (``deepsync.sources``), as ``deepsync detect --input`` runs it.
"""

from pathlib import Path

import numpy as np
import pytest

from deepsync.frontend.templates import SyncTemplates
from deepsync.testing.coherent import search_cells
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import RawFileSource, read_iq
from deepsync.sync.search import CellSearch
from deepsync.sync.stacking import FrameStacker, StackConfig
from deepsync.towers import load_tower_database

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO.parent / "shared" / "data" / "real_lte" / "f1860_s1.92_g0_1s_strong_rtlsdr.bin"
TOWERS = REPO / "config" / "towers" / "real_lte_1860.yaml"
# a 1 s recording: 10-frame stacks give the cell search ten looks (a walker's 100-frame default, one)
TEN_FRAMES = PipelineConfig().with_choices(n_frames=10)

pytestmark = pytest.mark.skipif(not RECORDING.exists(), reason=f"real recording not present at {RECORDING}")


@pytest.fixture(scope="module")
def iq():
    return read_iq(RECORDING, "cu8")


@pytest.fixture(scope="module")
def source():
    return RawFileSource(RECORDING, "cu8", 1.92e6)


@pytest.fixture(scope="module")
def reference(iq):
    """PCI -> coherent cell (sync-code start, frame length in samples, clock error)."""
    return {cell.pci: cell for cell in search_cells(iq)}


@pytest.fixture(scope="module")
def known(source):
    pipeline = Pipeline(source.frontend, TEN_FRAMES, towers=load_tower_database(TOWERS))
    return list(pipeline.run(source.chunks()))


def reference_error(cell, position: float) -> float:
    """Samples between an envelope code position and the nearest coherent code of that cell."""
    frames = round((position - cell.sync_position) / cell.samples_per_frame)
    return position - (cell.sync_position + frames * cell.samples_per_frame)


def test_the_reference_finds_the_two_cells(reference):
    assert {142, 86} <= set(reference)


def test_with_a_tower_database_it_names_142_and_86_and_nothing_else(known, reference):
    named = {c.pci for r in known for c in r.sync.cells}
    assert named == {142, 86}
    for result in known:
        for timing in result.timing.cells:
            error = reference_error(reference[timing.pci], timing.toa)
            assert abs(error) <= 2.0, f"PCI {timing.pci} {error:+.2f} samples from the coherent timing"
    # both are named from the third stack (three in a row confirm a cell), 142 from then on
    assert set(known[2].sync.pcis) == {142, 86}
    assert all(142 in r.sync.pcis for r in known[2:-1])


def test_the_receiver_clock_is_measured_from_the_envelope(known, reference):
    assert not known[0].sync.aligned  # +22 ppm uncompensated in the first stack: said, not hidden
    assert all(r.sync.aligned for r in known[1:])
    clock = reference[142].clock_ppm
    assert known[-1].sync.clock_drift_ppm == pytest.approx(clock, abs=1.0)


def test_blind_identity_at_the_true_timing(source, reference):
    """Blind, the envelope still ranks both true PCIs first among all 504 at their timing: the
    identity is in the envelope once timing and clock are right. (Finding the timing blind is
    harder: other periodic structure of this synchronised network competes with the codes.)"""
    templates = SyncTemplates(source.frontend)
    search = CellSearch(templates)
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=20, clock_ppm=reference[142].clock_ppm))
    stacks = [s for chunk in source.chunks() for s in stacker.push(chunk)]
    stacked = stacks[0].stacked()
    for pci in (142, 86):
        start = int(round(reference[pci].sync_position)) % (len(stacked) // 2)
        ranked = search._identify(stacked - stacked.mean(), start, 0.0).candidates
        assert ranked[0].pci == pci


def test_detect_names_the_same_cells_when_the_recording_uses_the_full_8_bit_range(tmp_path, capsys):
    """The recording scaled up 16x around mid-scale and clipped to 8 bits, as an RTL-SDR with more
    gain would have written it: its |x|^2 reaches 28800, which the fixed 0.5 per code of the old
    ``--iq`` could not hold in int16. Scaled from the recording's own peak, the envelope still
    names 142 and 86, and nothing else."""
    from deepsync.cli import main

    raw = np.fromfile(RECORDING, dtype=np.uint8).astype(np.float64)
    loud = tmp_path / "loud.cu8"  # the extension names the format
    np.clip(np.round(127.5 + 16 * (raw - 127.5)), 0, 255).astype(np.uint8).tofile(loud)
    summaries = {}
    for path in (RECORDING, loud):
        assert main(["detect", "--input", str(path), "--format", "cu8", "--rate", "1.92e6", "--towers", str(TOWERS)]) == 0
        out = capsys.readouterr().out
        summaries[path] = {int(line.split()[1]) for line in out.splitlines() if "reported in" in line}
    assert summaries[RECORDING] == summaries[loud] == {142, 86}
