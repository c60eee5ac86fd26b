"""The sampler's counter-based random numbers, mirrored in NumPy for oracles and tests.

``u(seed, camera, pixel, point)`` is a hash of the four integers, so a point's uniform does not
depend on the order in which the tree visits points. The native code (``csrc/core/rng.h``)
computes the same bits: ``h = mix(mix(mix(seed + C·(camera+1)) + pixel) + point)`` with the
SplitMix64 finaliser ``mix``, and ``u = ((h >> 11) + 0.5) · 2⁻⁵³ ∈ (0, 1)``.

Stratified draws (``stratified=True``) share one uniform per (camera, point),
``h = mix(mix(mix(seed + C·(camera+1)) ^ D) + point)``, shifted per pixel by the rank-1 lattice value
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


def uniforms(seed: int, camera: int, pixels: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Uniforms ``u [P, N]`` (float64 in (0,1)) for pixel ids ``pixels [P]`` and point ids ``points [N]``.

    Pixel id is ``row * width + col``; point id is the index into the op's input arrays.
    """
    with np.errstate(over="ignore"):
        s = _mix(np.asarray([seed], dtype=np.uint64) + _CAM * np.uint64(camera + 1))
        hp = _mix(s + np.asarray(pixels, dtype=np.uint64))
        h = _mix(hp[:, None] + np.asarray(points, dtype=np.uint64)[None, :])
    return ((h >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53


_STRAT = np.uint64(0x5851F42D4C957F2D)
_A1, _A2 = 0.7548776662466927, 0.5698402909980532


def stratified_uniforms(seed: int, camera: int, pixels: np.ndarray, points: np.ndarray,
                        width: int) -> np.ndarray:
    """Stratified uniforms ``u [P, N]`` (the native ``draw_uniform`` with ``stratified=True``)."""
    pixels = np.asarray(pixels, dtype=np.int64)
    with np.errstate(over="ignore"):
        s = _mix(_mix(np.asarray([seed], dtype=np.uint64) + _CAM * np.uint64(camera + 1)) ^ _STRAT)
        h = _mix(s + np.asarray(points, dtype=np.uint64))
    base = ((h >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    t = _A1 * (pixels % width).astype(np.float64) + _A2 * (pixels // width).astype(np.float64)
    shift = t - np.floor(t)
    u = base[None, :] + shift[:, None]
    u = u - np.floor(u)
    return np.where(u > 0.0, u, 2.0**-54)
