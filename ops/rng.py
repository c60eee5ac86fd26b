"""The sampler's counter-based random numbers, mirrored in NumPy for oracles and tests.

``u(seed, camera, pixel, point)`` is a hash of the four integers, so a point's uniform does not
depend on the order in which the tree visits points. The native code (``csrc/core/rng.h``)
computes the same bits: a pixel stream ``s = mix(mix(seed + C·(camera+1)) + pixel)`` (SplitMix64 finaliser
``mix``), two 32-bit hashes of each point ``hi = h32(lo32(s) + point·G)``, ``lo = h32(hi32(s) ^ point·G')``
(lowbias32 ``h32``), and ``u = ((hi·2²¹ + (lo >> 11)) + 0.5) · 2⁻⁵³ ∈ (0, 1)``.

Stratified draws (``stratified=True``) share one uniform per (camera, point), drawn as above from the
camera stream ``mix(mix(seed + C·(camera+1)) ^ D)``, shifted per pixel by the rank-1 lattice value
``φ(col, row) = frac(a1·col + a2·row)``: ``u = frac(h + φ)`` (``2⁻⁵⁴`` if that is exactly 0).
"""
from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_CAM = np.uint64(0xD1B54A32D192ED03)


def _mix(z: np.ndarray) -> np.ndarray:
    z = z + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def _hash32(x: np.ndarray) -> np.ndarray:
    """lowbias32 of uint32 words."""
    x = x ^ (x >> np.uint32(16))
    x = x * np.uint32(0x7FEB352D)
    x = x ^ (x >> np.uint32(15))
    x = x * np.uint32(0x846CA68B)
    return x ^ (x >> np.uint32(16))


def _point_uniforms(stream: np.ndarray, points: np.ndarray) -> np.ndarray:
    """u [S, N] of 64-bit streams ``stream [S]`` and point ids ``points [N]`` (native ``uniform01``)."""
    k = np.asarray(points, dtype=np.uint64).astype(np.uint32)[None, :]
    with np.errstate(over="ignore"):
        lo_word = (stream & np.uint64(0xFFFFFFFF)).astype(np.uint32)[:, None]
        hi_word = (stream >> np.uint64(32)).astype(np.uint32)[:, None]
        hi = _hash32(lo_word + k * np.uint32(0x9E3779B9))
        lo = _hash32(hi_word ^ (k * np.uint32(0x85EBCA6B)))
    h = (hi.astype(np.uint64) << np.uint64(21)) | (lo >> np.uint32(11)).astype(np.uint64)
    return (h.astype(np.float64) + 0.5) * 2.0**-53


def uniforms(seed: int, camera: int, pixels: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Uniforms ``u [P, N]`` (float64 in (0,1)) for pixel ids ``pixels [P]`` and point ids ``points [N]``.

    Pixel id is ``row * width + col``; point id is the index into the op's input arrays.
    """
    with np.errstate(over="ignore"):
        s = _mix(np.asarray([seed], dtype=np.uint64) + _CAM * np.uint64(camera + 1))
        hp = _mix(s + np.asarray(pixels, dtype=np.uint64))
    return _point_uniforms(hp, points)


_STRAT = np.uint64(0x5851F42D4C957F2D)
_A1, _A2 = 0.7548776662466927, 0.5698402909980532


def stratified_uniforms(seed: int, camera: int, pixels: np.ndarray, points: np.ndarray,
                        width: int) -> np.ndarray:
    """Stratified uniforms ``u [P, N]`` (the native ``draw_uniform`` with ``stratified=True``)."""
    pixels = np.asarray(pixels, dtype=np.int64)
    with np.errstate(over="ignore"):
        s = _mix(_mix(np.asarray([seed], dtype=np.uint64) + _CAM * np.uint64(camera + 1)) ^ _STRAT)
    base = _point_uniforms(s, points)[0]
    t = _A1 * (pixels % width).astype(np.float64) + _A2 * (pixels // width).astype(np.float64)
    shift = t - np.floor(t)
    u = base[None, :] + shift[:, None]
    u = u - np.floor(u)
    return np.where(u > 0.0, u, 2.0**-54)
