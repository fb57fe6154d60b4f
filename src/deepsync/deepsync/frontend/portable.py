"""Arithmetic that rounds the same on every CPU, so a seed gives the same ADC codes everywhere.

numpy chooses its SIMD kernels when it starts (SSE, AVX2 with FMA, AVX-512) and OpenBLAS its
own; a result one unit in the last place off flips an ADC code where a sample sits on a rounding
boundary. Exact on any kernel: elementwise +, -, *, / and sqrt of real floats (IEEE rounds each
once), comparisons, sorting, the FFT (pocketfft is compiled once, not chosen per CPU) and the
C library's functions (``math``, and numpy's complex ``exp``, which calls ``cexp``). Not exact:

* transcendental ufuncs on real arrays (``exp``, ``log``, ``log10``, ``sin``, ``cos``,
  ``power``, ``arctan2``, ...): numpy has AVX-512 kernels of its own for them;
* complex products: the AVX2 kernel rounds ``a*b - c*d`` once (fused multiply-add), SSE twice;
* the absolute value of complex arrays (an AVX-512 kernel) and every BLAS call (``@``, ``dot``,
  ``linalg.norm`` of a vector): the summation order belongs to the CPU's kernel.

The simulator uses the first kind and these helpers instead of the second; scalars go through
``math``. ``test_frontend.py`` runs a simulation under every SIMD kernel numpy offers on the
machine and under other OpenBLAS kernels and requires the same bits.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

_INTEGER_BITS = 52  # a double holds every integer below 2^53 exactly


def elementwise(function: Callable[..., float], *arrays: ArrayLike) -> np.ndarray:
    """``function`` (from ``math``) of every element (arrays broadcast): the C library's
    result, the same on any CPU. For the few values that set up a simulation, not samples."""
    values = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in arrays))
    if values[0].ndim == 0:
        return np.float64(function(*(float(v) for v in values)))
    flat = zip(*(v.ravel().tolist() for v in values))
    return np.array([function(*v) for v in flat], dtype=np.float64).reshape(values[0].shape)


def squared_magnitude(values: np.ndarray) -> np.ndarray:
    """|z|^2 of complex values, as Re^2 + Im^2."""
    return np.square(values.real) + np.square(values.imag)


def phasor(phase: np.ndarray | float) -> np.ndarray:
    """exp(j phase) (complex128), through the C library's ``cexp``."""
    return np.exp(1j * np.asarray(phase, dtype=np.float64))


def multiply(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Complex products of single-precision values (broadcast), the same bits on every CPU.

    In double precision the partial products of two floats are exact, so a fused and an
    unfused multiply-add round the same sum once; ``out`` (complex64) takes the rounded result.
    """
    return np.multiply(a, b, out=out, dtype=np.complex128, casting="same_kind")


def multiply_double(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Complex products of double-precision arrays (broadcast), one real operation at a time."""
    a, b = np.asarray(a, dtype=np.complex128), np.asarray(b, dtype=np.complex128)
    real = a.real * b.real
    real -= a.imag * b.imag
    imag = a.real * b.imag
    imag += a.imag * b.real
    out = np.empty(real.shape, dtype=np.complex128)
    out.real, out.imag = real, imag
    return out


class ExactProduct:
    """``left @ right`` of complex matrices for a fixed ``right`` (complex64 result), exact to
    2^-20 of each operand's largest entry and the same on every CPU.

    Both operands become integers (scaled by powers of two); every product and partial sum is
    then an integer below 2^53, which BLAS adds exactly in whatever order its kernel takes.
    """

    def __init__(self, right: np.ndarray) -> None:
        inner, columns = right.shape
        self.bits = (_INTEGER_BITS - math.ceil(math.log2(2 * inner))) // 2
        integers, self._scale = _integers(right, self.bits)
        # [Re L | Im L] @ this = Re LR and Im LR, interleaved as complex numbers are
        self._right = np.empty((2 * inner, columns, 2))
        self._right[:inner, :, 0] = integers.real
        self._right[:inner, :, 1] = integers.imag
        self._right[inner:, :, 0] = -integers.imag
        self._right[inner:, :, 1] = integers.real
        self._right = self._right.reshape(2 * inner, 2 * columns)

    def __call__(self, left: np.ndarray) -> np.ndarray:
        integers, scale = _integers(left, self.bits)
        product = np.concatenate([integers.real, integers.imag], axis=1) @ self._right
        product *= scale * self._scale  # a power of two: exact
        return product.astype(np.float32).view(np.complex64)


def _integers(values: np.ndarray, bits: int) -> tuple[np.ndarray, float]:
    """``values`` as complex integers of at most ``bits`` bits per part, and the power of two
    that scales them back."""
    largest = max(float(np.max(np.abs(values.real), initial=0.0)), float(np.max(np.abs(values.imag), initial=0.0)))
    if largest == 0.0:
        return np.zeros(values.shape, dtype=np.complex128), 1.0
    scale = math.ldexp(1.0, math.frexp(largest)[1] - bits)  # largest / scale < 2^bits
    return np.rint(values * (1.0 / scale)), scale
