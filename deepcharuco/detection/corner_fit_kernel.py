"""`corner_fit`'s Gauss-Newton iterations compiled by numba, one corner at a time: the same arithmetic as its numpy
path (`corner_fit._iterate`), without numpy's per-call overhead, which is most of that path's time on a frame's
few corners (a 16-corner frame's fit on a 2-core CPU: ~3.6 ms with numpy's iterations, ~2.3 ms with these).

Imported only where numba is installed (``pip install deepcharuco[fast]``); `corner_fit` uses the numpy path
otherwise. The first call compiles (a few seconds, cached on disk beside this file where it is writable).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SQRT_HALF = math.sqrt(0.5)
ROOT = 1.0 / math.sqrt(2.0 * math.pi)


@njit(cache=True)
def _ndtr(z: float) -> float:
    return 0.5 * math.erfc(-z * SQRT_HALF)


@njit(cache=True)
def _model(value, along0, along1, normals, margin0, margin1, black, p, jacobian_row) -> float:
    """One pixel's residual (model minus ``value``) at ``p`` (6,), its Jacobian row written into ``jacobian_row``."""
    sigma0, sigma1 = math.exp(p[2]), math.exp(p[3])
    shift0 = normals[0, 0] * p[0] + normals[0, 1] * p[1]
    shift1 = normals[1, 0] * p[0] + normals[1, 1] * p[1]
    a0, a1 = along0 - shift0, (along1 - shift1) * black
    z00, z01 = a0 / sigma0, a1 / sigma1
    zp0, zp1 = (a0 - margin0) / sigma0, (a1 - margin1) / sigma1
    zm0, zm1 = (-a0 - margin0) / sigma0, (-a1 - margin1) / sigma1
    f00, f01 = _ndtr(z00), _ndtr(z01)
    fp0, fp1 = _ndtr(zp0), _ndtr(zp1)
    fm0, fm1 = _ndtr(zm0), _ndtr(zm1)
    ink = f00 * f01 + (1.0 - f00) * (1.0 - f01) + fp0 * fm1 + fm0 * fp1
    p00, p01 = math.exp(-0.5 * z00 * z00) * ROOT, math.exp(-0.5 * z01 * z01) * ROOT
    pp0, pp1 = math.exp(-0.5 * zp0 * zp0) * ROOT, math.exp(-0.5 * zp1 * zp1) * ROOT
    pm0, pm1 = math.exp(-0.5 * zm0 * zm0) * ROOT, math.exp(-0.5 * zm1 * zm1) * ROOT
    # each line's derivatives take the other line's factors
    d_along0 = (p00 * (2.0 * f01 - 1.0) + pp0 * fm1 - pm0 * fp1) / sigma0
    d_along1 = (p01 * (2.0 * f00 - 1.0) + pp1 * fm0 - pm1 * fp0) / sigma1
    d_sigma0 = -(p00 * z00 * (2.0 * f01 - 1.0) + pp0 * zp0 * fm1 + pm0 * zm0 * fp1)
    d_sigma1 = -(p01 * z01 * (2.0 * f00 - 1.0) + pp1 * zp1 * fm0 + pm1 * zm1 * fp0)
    beta = p[5]
    # d along / d shift = -flip n (flip = (1, black))
    jacobian_row[0] = beta * (d_along0 * normals[0, 0] + d_along1 * black * normals[1, 0])
    jacobian_row[1] = beta * (d_along0 * normals[0, 1] + d_along1 * black * normals[1, 1])
    jacobian_row[2] = -beta * d_sigma0
    jacobian_row[3] = -beta * d_sigma1
    jacobian_row[4] = 1.0
    jacobian_row[5] = -ink
    return p[4] - beta * ink - value


@njit(cache=True)
def _normal_equations(values, weights, along, normals, margins, black, p, normal, gradient) -> float:
    """J^T W J and J^T W r at ``p`` into ``normal`` (6, 6) and ``gradient`` (6,); returns the weighted cost."""
    normal[:] = 0.0
    gradient[:] = 0.0
    row = np.empty(6)
    cost = 0.0
    for m in range(values.shape[0]):
        w = weights[m]
        if w == 0.0:
            continue
        r = _model(values[m], along[m, 0], along[m, 1], normals, margins[0], margins[1], black, p, row)
        cost += w * r * r
        for i in range(6):
            wi = w * row[i]
            gradient[i] += wi * r
            for j in range(6):
                normal[i, j] += wi * row[j]
    return cost


@njit(cache=True)
def _solve6(matrix, vector, out) -> None:
    """``matrix`` x = ``vector`` by Gaussian elimination with partial pivoting; a singular system gives x = 0."""
    a = matrix.copy()
    b = vector.copy()
    n = 6
    for k in range(n):
        pivot = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[pivot, k]):
                pivot = i
        if a[pivot, k] == 0.0 or not math.isfinite(a[pivot, k]):
            out[:] = 0.0
            return
        if pivot != k:
            for j in range(n):
                a[k, j], a[pivot, j] = a[pivot, j], a[k, j]
            b[k], b[pivot] = b[pivot], b[k]
        for i in range(k + 1, n):
            factor = a[i, k] / a[k, k]
            for j in range(k, n):
                a[i, j] -= factor * a[k, j]
            b[i] -= factor * b[k]
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total -= a[i, j] * out[j]
        out[i] = total / a[i, i]


@njit(cache=True)
def iterate(values, weights, along, normals, margins, black, params, iterations, damping, max_step, max_log_blur_step,
            log_blur_low, log_blur_high, converged):
    """`corner_fit._iterate` compiled: Gauss-Newton steps of (N,) corners' ``params`` (N, 6), updated in place, all in
    step until a step was shorter than ``converged`` px for every corner (or ``iterations``). Returns (start cost
    (N,), final cost (N,), final normal matrices (N, 6, 6))."""
    n = values.shape[0]
    start_cost = np.empty(n)
    cost = np.empty(n)
    normal = np.empty((n, 6, 6))
    gradient = np.empty((n, 6))
    damped = np.empty((6, 6))
    step = np.empty(6)
    for c in range(n):
        start_cost[c] = _normal_equations(values[c], weights[c], along[c], normals[c], margins[c], black[c], params[c],
                                          normal[c], gradient[c])
        cost[c] = start_cost[c]
    for _ in range(iterations):
        every_short = True
        for c in range(n):
            p = params[c]
            damped[:] = normal[c]
            for i in range(6):
                damped[i, i] += damping * max(normal[c, i, i], 1e-9)
            _solve6(damped, -gradient[c], step)
            length = math.sqrt(step[0] * step[0] + step[1] * step[1])
            if not length < converged:  # NaN too, as numpy's all(length < converged)
                every_short = False
            scale = min(1.0, max_step / max(length, 1e-12))
            for i in range(6):
                step[i] *= scale
            for i in (2, 3):
                step[i] = min(max(step[i], -max_log_blur_step), max_log_blur_step)
            for i in range(6):
                p[i] += step[i]
            for i in (2, 3):
                p[i] = min(max(p[i], log_blur_low), log_blur_high)
            cost[c] = _normal_equations(values[c], weights[c], along[c], normals[c], margins[c], black[c], p,
                                        normal[c], gradient[c])
        if every_short:
            break
    return start_cost, cost, normal
