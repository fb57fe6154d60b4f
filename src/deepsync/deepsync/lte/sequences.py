"""Downlink physical-layer sequences of TS 36.211: PSS (§6.11.1), SSS (§6.11.2), CRS (§6.10.1).

Each function returns the frequency-domain values exactly as the standard defines them, in
the order they are mapped to subcarriers (see :mod:`deepsync.lte.grid` for the mapping).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from deepsync.lte.cell import N_CELL_IDS

PSS_ROOTS = {0: 25, 1: 29, 2: 34}  # Zadoff-Chu root index u per N_ID^(2), Table 6.11.1.1-1
SYNC_LENGTH = 62
N_ID1_COUNT = 168
_GOLD_NC = 1600


def _check_id(name: str, value: int, count: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value < count:
        raise ValueError(f"{name} must be an integer in 0..{count - 1}, got {value!r}")
    return int(value)


@lru_cache(maxsize=3)
def _pss(n_id_2: int) -> np.ndarray:
    u = PSS_ROOTS[n_id_2]
    n = np.arange(SYNC_LENGTH)
    # d_u(n) = exp(-j pi u n (n+1) / 63) for n <= 30, and with (n+1)(n+2) for n >= 31: the
    # length-63 Zadoff-Chu sequence with its middle element (the DC position) punctured.
    m = np.where(n <= 30, n * (n + 1), (n + 1) * (n + 2))
    d = np.exp(-1j * np.pi * u * m / 63)
    d.flags.writeable = False
    return d


def pss(n_id_2: int) -> np.ndarray:
    """The 62 PSS values d(0..61) for ``n_id_2`` in {0, 1, 2} (complex, unit modulus)."""
    return _pss(_check_id("n_id_2", n_id_2, 3))


def _m_sequence(taps: tuple[int, ...]) -> np.ndarray:
    """Length-31 binary m-sequence x(i+5) = sum of x(i+t) mod 2, x(0..4) = 0,0,0,0,1."""
    x = np.zeros(31, dtype=np.int64)
    x[4] = 1
    for i in range(26):
        x[i + 5] = sum(x[i + t] for t in taps) % 2
    return 1 - 2 * x


_S_TILDE = _m_sequence((2, 0))
_C_TILDE = _m_sequence((3, 0))
_Z_TILDE = _m_sequence((4, 2, 1, 0))


def sss_indices(n_id_1: int) -> tuple[int, int]:
    """(m0, m1) cyclic shifts of the SSS m-sequences for ``n_id_1`` (Table 6.11.2.1-1)."""
    n_id_1 = _check_id("n_id_1", n_id_1, N_ID1_COUNT)
    q_prime = n_id_1 // 30
    q = (n_id_1 + q_prime * (q_prime + 1) // 2) // 30
    m_prime = n_id_1 + q * (q + 1) // 2
    m0 = m_prime % 31
    m1 = (m0 + m_prime // 31 + 1) % 31
    return m0, m1


@lru_cache(maxsize=2 * N_CELL_IDS)
def _sss(n_id_1: int, n_id_2: int, subframe: int) -> np.ndarray:
    m0, m1 = sss_indices(n_id_1)
    n = np.arange(31)
    s0 = _S_TILDE[(n + m0) % 31]
    s1 = _S_TILDE[(n + m1) % 31]
    c0 = _C_TILDE[(n + n_id_2) % 31]
    c1 = _C_TILDE[(n + n_id_2 + 3) % 31]
    z1_m0 = _Z_TILDE[(n + m0 % 8) % 31]
    z1_m1 = _Z_TILDE[(n + m1 % 8) % 31]
    d = np.empty(SYNC_LENGTH)
    if subframe == 0:
        d[0::2] = s0 * c0
        d[1::2] = s1 * c1 * z1_m0
    else:
        d[0::2] = s1 * c0
        d[1::2] = s0 * c1 * z1_m1
    d.flags.writeable = False
    return d


def sss(n_id_1: int, n_id_2: int, subframe: int) -> np.ndarray:
    """The 62 SSS values d(0..61) (real, +-1) for subframe 0 or 5.

    The two halves swap between subframes 0 and 5, which is how a receiver tells the first
    half-frame from the second.
    """
    if subframe not in (0, 5):
        raise ValueError(f"the SSS is sent in subframes 0 and 5, not {subframe!r}")
    return _sss(_check_id("n_id_1", n_id_1, N_ID1_COUNT), _check_id("n_id_2", n_id_2, 3), subframe)


def _lfsr(initial: np.ndarray, taps: tuple[int, ...], length: int) -> np.ndarray:
    """x(n+31) = XOR of x(n+t) for t in taps; advances 28 bits per step (smallest gap 31-3)."""
    x = np.zeros(length + 31, dtype=np.uint8)
    x[:31] = initial
    for n in range(0, length, 28):
        stop = min(n + 28, length)
        acc = np.zeros(stop - n, dtype=np.uint8)
        for t in taps:
            acc ^= x[n + t : stop + t]
        x[n + 31 : stop + 31] = acc
    return x[:length]


_X1 = _lfsr(np.eye(1, 31, 0, dtype=np.uint8)[0], (3, 0), _GOLD_NC + 4 * 110)
# x2 is linear (over GF(2)) in its 31 initial bits: the sequence from each single bit, kept, and
# any c_init's x2 is the XOR of those its bits select (a CRS's 440 bits in ~10 us, not 0.2 ms)
_X2_FROM_BIT = np.stack([_lfsr(np.eye(1, 31, bit, dtype=np.uint8)[0], (3, 2, 1, 0), len(_X1)) for bit in range(31)])


def gold_sequence(c_init: int, length: int) -> np.ndarray:
    """Pseudo-random sequence c(n) of §7.2 (length-31 Gold code, Nc = 1600), as 0/1 bits."""
    bits = ((c_init >> np.arange(31)) & 1).astype(np.uint8)
    if length <= len(_X1) - _GOLD_NC:
        x1 = _X1
        x2 = (bits @ _X2_FROM_BIT[:, : _GOLD_NC + length]) & 1  # at most 31 ones summed: no overflow
    else:
        x1 = _lfsr(_X1[:31], (3, 0), _GOLD_NC + length)
        x2 = _lfsr(bits, (3, 2, 1, 0), _GOLD_NC + length)
    return x1[_GOLD_NC : _GOLD_NC + length] ^ x2[_GOLD_NC:]


def crs(n_cell_id: int, slot: int, symbol: int, n_rb_max: int = 110) -> np.ndarray:
    """CRS values r_{l,ns}(m), m = 0..2*n_rb_max-1, normal CP (N_CP = 1), §6.10.1.1.

    A carrier with N_RB resource blocks uses m' = m + n_rb_max - N_RB for its m = 0..2N_RB-1
    (the centre of the full-length sequence), see :func:`deepsync.lte.grid.crs_positions`.
    """
    n_cell_id = _check_id("n_cell_id", n_cell_id, N_CELL_IDS)
    slot = _check_id("slot", slot, 20)
    symbol = _check_id("symbol", symbol, 7)
    c_init = 2**10 * (7 * (slot + 1) + symbol + 1) * (2 * n_cell_id + 1) + 2 * n_cell_id + 1
    c = gold_sequence(c_init, 4 * n_rb_max).astype(np.float64)
    return ((1 - 2 * c[0::2]) + 1j * (1 - 2 * c[1::2])) / np.sqrt(2)
