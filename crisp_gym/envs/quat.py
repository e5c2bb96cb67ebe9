"""Quaternion helpers over arrays (w, x, y, z), broadcasting over leading dimensions.

Small and allocation-light on purpose: the batched env calls them on (N, 24, 4) arrays every
control step, where object-based rotation libraries cost more than the arithmetic.

Rotation matrices (:func:`matrix`, :func:`matrix_pair`, :func:`tangent_normal`) come from one
matrix product: every entry of a unit quaternion's matrix is a fixed combination of the ten
products ``q_i q_j`` and 1 (``1 - 2 (y² + z²)``, ``2 (x y + w z)``, ...). The products are
formed over contiguous component rows and BLAS does the rest, where the same formulas as
elementwise operations on (..., 4) arrays cost a strided pass and a temporary each. With
coefficients 0 and ±2 and the constant added last, each entry rounds exactly as the formula.
"""

from __future__ import annotations

import numpy as np


def _matrix_coefficients() -> np.ndarray:
    """(11, 9): row-major R = [ww wx wy wz xx xy xz yy yz zz 1] @ coefficients."""
    _, wx, wy, wz, xx, xy, xz, yy, yz, zz, one = range(11)
    terms = {  # entry (row, col): [(product, coefficient), ...], the constant last
        (0, 0): [(yy, -2), (zz, -2), (one, 1)], (0, 1): [(xy, 2), (wz, -2)], (0, 2): [(xz, 2), (wy, 2)],
        (1, 0): [(xy, 2), (wz, 2)], (1, 1): [(xx, -2), (zz, -2), (one, 1)], (1, 2): [(yz, 2), (wx, -2)],
        (2, 0): [(xz, 2), (wy, -2)], (2, 1): [(yz, 2), (wx, 2)], (2, 2): [(xx, -2), (yy, -2), (one, 1)],
    }
    coef = np.zeros((11, 3, 3))
    for (row, col), pairs in terms.items():
        for product, value in pairs:
            coef[product, row, col] = value
    return coef.reshape(11, 9)


_MATRIX_COEF = _matrix_coefficients()
_TANGENT_NORMAL_COEF = np.ascontiguousarray(_MATRIX_COEF[:, [0, 3, 6, 2, 5, 8]])  # columns 0 and 2 of R
_PAIR_COEF = np.zeros((11, 2, 3, 2, 3))  # blockdiag(R, R)
_PAIR_COEF[:, 0, :, 0, :] = _PAIR_COEF[:, 1, :, 1, :] = _MATRIX_COEF.reshape(11, 3, 3)
_PAIR_COEF = _PAIR_COEF.reshape(11, 36)


def _linear_in_products(q: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """(..., K) ``[ww wx wy wz xx xy xz yy yz zz 1] @ coef`` for quaternions q (..., 4)."""
    q = np.asarray(q)
    dtype = np.result_type(q, 1.0)
    comp = np.ascontiguousarray(q.reshape(-1, 4).T, dtype=dtype)  # (4, M): components as rows
    products = np.empty((11, comp.shape[1]), dtype=dtype)
    np.multiply(comp[0], comp, out=products[0:4])
    np.multiply(comp[1], comp[1:], out=products[4:7])
    np.multiply(comp[2], comp[2:], out=products[7:9])
    np.multiply(comp[3], comp[3], out=products[9])
    products[10] = 1.0
    out = products.T @ coef.astype(dtype, copy=False)  # one BLAS call
    return out.reshape(*q.shape[:-1], coef.shape[1])


def conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b over the last axis (np.cross spends most of its time on axis bookkeeping)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)), dtype=np.result_type(a, b))
    np.subtract(ay * bz, az * by, out=out[..., 0])
    np.subtract(az * bx, ax * bz, out=out[..., 1])
    np.subtract(ax * by, ay * bx, out=out[..., 2])
    return out


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def yaw(q: np.ndarray) -> np.ndarray:
    """(...,) q's heading: the angle about +z of its rotated x axis."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quat(q: np.ndarray) -> np.ndarray:
    """The heading part of q: a rotation about +z by q's yaw."""
    half = yaw(q) / 2
    out = np.zeros(q.shape)
    out[..., 0] = np.cos(half)
    out[..., 3] = np.sin(half)
    return out


def inverse_yaw_matrix(yaw_angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) M such that the row vector ``v @ M`` is v rotated by −yaw about +z.

    For ``yaw_angle = yaw(q)`` that is ``rotate(conjugate(yaw_quat(q)), v)``: v in q's heading
    frame, for many vectors at once by a matrix product.
    """
    c, s = np.cos(yaw_angle), np.sin(yaw_angle)
    out = np.zeros((*np.shape(yaw_angle), 3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def angle(q: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, π] of unit quaternions."""
    return 2.0 * np.arccos(np.clip(np.abs(q[..., 0]), 0.0, 1.0))


def matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of unit quaternions (..., 4)."""
    return _linear_in_products(q, _MATRIX_COEF).reshape(*np.shape(q)[:-1], 3, 3)


def matrix_pair(q: np.ndarray) -> np.ndarray:
    """(..., 6, 6) ``[[R, 0], [0, R]]`` for each quaternion's matrix R.

    For row vectors a, b: ``[a, b] @ matrix_pair(q) = [Rᵀa, Rᵀb]``, i.e. both axes of a
    :func:`tangent_normal` pair taken into q's frame by one matrix product.
    """
    return _linear_in_products(q, _PAIR_COEF).reshape(*np.shape(q)[:-1], 6, 6)


def tangent_normal(q: np.ndarray) -> np.ndarray:
    """(..., 6) continuous rotation features: the rotated x and z axes (matrix columns 0, 2)."""
    return _linear_in_products(q, _TANGENT_NORMAL_COEF)
