"""Reproducible random streams, one per (scenario seed, site, purpose).

Keying streams by the site's *name* (not its index) means adding, removing or reordering sites
leaves every other site's draws unchanged.
"""

from __future__ import annotations

import zlib

import numpy as np


def site_rng(seed: int, site: str, purpose: str) -> np.random.Generator:
    """Generator for one purpose (e.g. ``"fading"``) of one site, determined by the seed."""
    key = zlib.crc32(f"{site}\0{purpose}".encode("utf-8"))
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(key,)))


def transmit_chain_phase(seed: int, site: str, cell_key: int) -> float:
    """A sector's own transmit-chain phase (rad, uniform in [0, 2 pi)): a fixed phase of its PA,
    feeder and antenna on every path it sends, which sets the stable cross term of co-sited
    sectors at the receiver. ``cell_key`` names the cell within its site (its PCI)."""
    return float(site_rng(seed, site, f"chain phase {cell_key}").uniform(0, 2 * np.pi))
