"""`corner_fit`'s windows and Gauss-Newton iterations compiled by numba, one corner at a time: the same pixels and
arithmetic as its numpy path (`corner_fit._windows`, `corner_fit._iterate`), without numpy's per-call overhead,
which is most of that path's time on a frame's few corners.

Imported only where numba is installed (``pip install deepcharuco[fast]``); `corner_fit` uses the numpy path
otherwise. The first call compiles (a few seconds, cached on disk beside this file where it is writable).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

ROOT = 1.0 / math.sqrt(2.0 * math.pi)
# `corner_fit.NDTR_*`: erfc by Abramowitz & Stegun 7.1.26 on the pdf's own exponential
P, A1, A2, A3, A4, A5 = 0.3275911 * math.sqrt(0.5), 0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429


@njit(cache=True)
def _cdf_pdf(z: float) -> tuple[float, float]:
    """(the standard normal's cdf, its pdf) at ``z``: `corner_fit._cdf_pdf` for one number."""
    e = math.exp(-0.5 * z * z)
    t = 1.0 / (1.0 + P * abs(z))
    tail = 0.5 * t * (A1 + t * (A2 + t * (A3 + t * (A4 + t * A5)))) * e
    return (tail if z < 0.0 else 1.0 - tail), e * ROOT


@njit(cache=True)
def _model(value, along0, along1, normals, margin0, margin1, black, p, sigma0, sigma1, shift0, shift1,
           jacobian_row) -> float:
    """One pixel's residual (model minus ``value``) at ``p`` (6,), its Jacobian row written into ``jacobian_row``;
    ``sigma0``, ``sigma1``: exp(``p[2:4]``), ``shift0``, ``shift1``: the shift ``p[:2]`` along the ``normals``."""
    a0, a1 = along0 - shift0, (along1 - shift1) * black
    z00, z01 = a0 / sigma0, a1 / sigma1
    zp0, zp1 = (a0 - margin0) / sigma0, (a1 - margin1) / sigma1
    zm0, zm1 = (-a0 - margin0) / sigma0, (-a1 - margin1) / sigma1
    f00, p00 = _cdf_pdf(z00)
    f01, p01 = _cdf_pdf(z01)
    fp0, pp0 = _cdf_pdf(zp0)
    fp1, pp1 = _cdf_pdf(zp1)
    fm0, pm0 = _cdf_pdf(zm0)
    fm1, pm1 = _cdf_pdf(zm1)
    ink = f00 * f01 + (1.0 - f00) * (1.0 - f01) + fp0 * fm1 + fm0 * fp1
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
def _normal_equations(values, along, count, normals, margins, black, p, normal, gradient) -> float:
    """J^T J and J^T r over a window's first ``count`` pixels at ``p`` into ``normal`` (6, 6) and ``gradient`` (6,);
    returns the cost (the sum of squared residuals)."""
    normal[:] = 0.0
    gradient[:] = 0.0
    row = np.empty(6)
    cost = 0.0
    sigma0, sigma1 = math.exp(p[2]), math.exp(p[3])
    shift0 = normals[0, 0] * p[0] + normals[0, 1] * p[1]
    shift1 = normals[1, 0] * p[0] + normals[1, 1] * p[1]
    for m in range(count):
        r = _model(values[m], along[m, 0], along[m, 1], normals, margins[0], margins[1], black, p, sigma0, sigma1,
                   shift0, shift1, row)
        cost += r * r
        for i in range(6):
            gradient[i] += row[i] * r
            for j in range(i, 6):
                normal[i, j] += row[i] * row[j]
    for i in range(6):
        for j in range(i):
            normal[i, j] = normal[j, i]
    return cost


@njit(cache=True)
def _solve6(matrix, vector, out) -> bool:
    """``matrix`` x = ``vector`` by Gaussian elimination with partial pivoting into ``out``; a singular system gives
    x = 0 and False."""
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
            return False
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
    return True


@njit(cache=True)
def fit_windows(smooth, x0, y0, width, height, origin, start, to_board, normals, margins, black, usable, reach, half,
                log_start_sigma, iterations, damping, max_step, max_log_blur_step, log_blur_low, log_blur_high,
                converged):
    """`corner_fit`'s windows and iterations for (N,) corners, compiled.

    Each corner's window: the pixels of the (2 ``half`` + 1)^2 grid about its ``origin`` (N, 2) (the start's
    nearest pixel) inside the ``width`` x ``height`` image whose offsets from ``start`` (N, 2), taken to board
    squares by ``to_board`` (N, 2, 2), are within ``reach`` along both; none where ``usable`` (N,) is False. Their
    values come from ``smooth``, the image's region from (``x0``, ``y0``) blurred. Then Gauss-Newton from the
    window's paper level and contrast and blurs of exp(``log_start_sigma``), each corner until its step was shorter
    than ``converged`` px (or ``iterations``).

    Returns (params (N, 6): shift x, y, log blurs, alpha, beta; the cost at the start (N,), at the end (N,); the
    corner block (N, 2, 2) of the inverse of the normal matrix J^T J there, NaN where it is singular or not finite;
    the window's pixels (N,))."""
    n = start.shape[0]
    side = 2 * half + 1
    params = np.zeros((n, 6))
    start_cost = np.zeros(n)
    cost = np.zeros(n)
    normal = np.zeros((6, 6))
    spread = np.full((n, 2, 2), np.nan)
    unit = np.zeros(6)
    column = np.empty(6)
    count = np.zeros(n, np.int64)
    values = np.empty(side * side)
    along = np.empty((side * side, 2))
    gradient = np.empty(6)
    damped = np.empty((6, 6))
    step = np.empty(6)
    for c in range(n):
        m = 0
        low, high = np.inf, -np.inf
        if usable[c]:
            for gy in range(-half, half + 1):
                for gx in range(-half, half + 1):
                    x, y = origin[c, 0] + gx, origin[c, 1] + gy
                    if x < 0 or x >= width or y < 0 or y >= height:
                        continue
                    dx, dy = x - start[c, 0], y - start[c, 1]
                    s = to_board[c, 0, 0] * dx + to_board[c, 0, 1] * dy
                    t = to_board[c, 1, 0] * dx + to_board[c, 1, 1] * dy
                    if max(abs(s), abs(t)) > reach:
                        continue
                    value = float(smooth[int(y) - y0, int(x) - x0])
                    values[m] = value
                    along[m, 0] = normals[c, 0, 0] * dx + normals[c, 0, 1] * dy
                    along[m, 1] = normals[c, 1, 0] * dx + normals[c, 1, 1] * dy
                    low, high = min(low, value), max(high, value)
                    m += 1
        count[c] = m
        p = params[c]
        p[2] = p[3] = log_start_sigma
        # the paper's level and the contrast from the window's extremes; an empty window: nothing to fit
        p[4], p[5] = (high, high - low) if m > 0 else (0.0, 0.0)
        start_cost[c] = _normal_equations(values, along, m, normals[c], margins[c], black[c], p, normal, gradient)
        cost[c] = start_cost[c]
        for _ in range(iterations):
            damped[:] = normal
            for i in range(6):
                damped[i, i] += damping * max(normal[i, i], 1e-9)
            _solve6(damped, -gradient, step)
            length = math.sqrt(step[0] * step[0] + step[1] * step[1])
            scale = min(1.0, max_step / max(length, 1e-12))
            for i in range(6):
                step[i] *= scale
            for i in (2, 3):
                step[i] = min(max(step[i], -max_log_blur_step), max_log_blur_step)
            for i in range(6):
                p[i] += step[i]
            for i in (2, 3):
                p[i] = min(max(p[i], log_blur_low), log_blur_high)
            cost[c] = _normal_equations(values, along, m, normals[c], margins[c], black[c], p, normal, gradient)
            if length < converged:
                break
        if np.all(np.isfinite(normal)):
            for j in range(2):
                unit[:] = 0.0
                unit[j] = 1.0
                if _solve6(normal, unit, column):
                    spread[c, 0, j], spread[c, 1, j] = column[0], column[1]
                else:
                    spread[c] = np.nan
                    break
    return params, start_cost, cost, spread, count
