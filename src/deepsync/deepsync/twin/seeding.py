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
