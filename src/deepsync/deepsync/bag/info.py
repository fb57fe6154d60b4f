"""What a bag holds (``deepsync info`` prints it): topics, counts, length, integrity, what made
it and the ground truth it carries."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .convert import cell_timing_array_from_msg
from .errors import BagError
from .mcapfile import CrcStatus
from .reader import BagInconsistency, BagReader
from .topics import TRUTH_CELL_TIMING_TOPIC
from .writer import PROVENANCE_KEY, provenance_document


@dataclass(frozen=True)
class BagInfo:
    path: Path
    message_count: int
    duration_s: float
    topics: tuple[tuple[str, str, int], ...]  # (topic, message type, messages), by topic
    crc: CrcStatus
    notes: tuple[BagInconsistency, ...]  # where metadata.yaml disagrees with the MCAP file
    provenance: dict | None  # what made the bag (None: no provenance record)
    provenance_error: str | None  # why a provenance record could not be read
    truth_codes: dict[int, int] | None  # PCI -> its true sync-code arrivals, by PCI (None: no truth topic)


def bag_info(path: str | Path) -> BagInfo:
    """``path``'s contents, read once through (the truth topic's messages, to count the cells)."""
    path = Path(path)
    with BagReader(path) as bag:
        provenance, provenance_error = None, None
        text = bag.custom_data.get(PROVENANCE_KEY)
        if text:
            try:
                provenance = provenance_document(text, path)
            except BagError as error:
                provenance_error = str(error)
        truth_codes = None
        if TRUTH_CELL_TIMING_TOPIC in bag.topics:
            truth_codes = {}
            for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
                for record in cell_timing_array_from_msg(item.message).cells:
                    truth_codes[record.pci] = truth_codes.get(record.pci, 0) + 1
            truth_codes = dict(sorted(truth_codes.items()))
        return BagInfo(
            path=path,
            message_count=bag.message_count,
            duration_s=bag.duration_ns / 1e9,
            topics=tuple((topic, msgtype, bag.message_counts[topic]) for topic, msgtype in sorted(bag.topics.items())),
            crc=bag.crc_status,
            notes=tuple(bag.inconsistencies),
            provenance=provenance,
            provenance_error=provenance_error,
            truth_codes=truth_codes,
        )
