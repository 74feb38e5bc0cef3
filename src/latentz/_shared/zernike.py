"""Real Zernike polynomials in Noll's order, on the unit disk that circumscribes the image field.

The paper models how aberrations vary across the field with the first 400 Zernike polynomials of
Noll's indexing (Supp. Table 2), here used in real space: the polynomial argument is the lateral
position in the image, not a pupil coordinate.

Conventions
-----------
*Indexing.* Noll, J. Opt. Soc. Am. 66, 207 (1976): ``j = 1, 2, ...``; within a radial order ``n``
the azimuthal order ``|m|`` increases; for ``m != 0`` the even ``j`` of each pair carries
``cos(|m| theta)`` and the odd ``j`` carries ``sin(|m| theta)``. So ``Z2 = 2 rho cos(theta)``,
``Z3 = 2 rho sin(theta)``, ``Z5 = sqrt(6) rho^2 sin(2 theta)``, ``Z6 = sqrt(6) rho^2 cos(2 theta)``.

*Normalisation.* Noll's: each polynomial has unit root-mean-square over the unit disk,
``(1 / pi) * integral Z_j Z_k dA = delta_jk``; the factor is ``sqrt(n + 1)`` for ``m = 0`` and
``sqrt(2 (n + 1))`` otherwise.

*Radial polynomials* come from Kintner's three-term recurrence in ``n`` at fixed ``m``
(Kintner, Optica Acta 23, 679 (1976)), which is stable on ``0 <= rho <= 1``; the explicit
factorial sum is not used because it cancels catastrophically at high order.

*Field to disk.* A field of ``(H, W)`` pixels covers ``x`` in ``[-0.5, W - 0.5]`` and ``y`` in
``[-0.5, H - 0.5]`` (pixel edges). Its centre ``((W - 1) / 2, (H - 1) / 2)`` maps to the disk's
centre and its corners to the unit circle: ``rho = r / R`` with ``R = hypot(W, H) / 2``, and
``theta = atan2(y - yc, x - xc)``. The whole rectangle therefore lies inside the disk, and the basis
is *not* orthogonal over the rectangle, which is why coefficients are always found by least
squares, never by inner products.
"""

from __future__ import annotations

import numpy as np

from latentz._shared.validate import check_array, check_int, check_positive

__all__ = [
    "noll_to_nm",
    "zernike_polar",
    "field_to_disk",
    "zernike_design",
    "lstsq_operator",
    "truncated_lstsq_operator",
    "press_terms",
    "fit_zernike",
]

_CHUNK = 16384  # points per block when building a design matrix


def noll_to_nm(n_terms: int) -> tuple[np.ndarray, np.ndarray]:
    """Radial order ``n`` and signed azimuthal order ``m`` of Noll indices ``1 ... n_terms``.

    ``m > 0`` means a ``cos(m theta)`` term and ``m < 0`` a ``sin(|m| theta)`` term.

    Examples
    --------
    >>> n, m = noll_to_nm(6)
    >>> n.tolist(), m.tolist()
    ([0, 1, 1, 2, 2, 2], [0, 1, -1, 0, -2, 2])
    """
    n_terms = check_int("n_terms", n_terms, minimum=1)
    orders_n, orders_m = [], []
    n = 0
    while len(orders_n) < n_terms:
        j = n * (n + 1) // 2 + 1  # first Noll index of radial order n
        for am in range(n % 2, n + 1, 2):
            if am == 0:
                orders_n.append(n)
                orders_m.append(0)
                j += 1
                continue
            for jj in (j, j + 1):  # even j: cosine, odd j: sine
                orders_n.append(n)
                orders_m.append(am if jj % 2 == 0 else -am)
            j += 2
        n += 1
    return np.array(orders_n[:n_terms]), np.array(orders_m[:n_terms])


def _radial_table(rho: np.ndarray, needed: set[tuple[int, int]]) -> dict:
    """``R_n^m(rho)`` for every ``(n, m)`` in ``needed`` (m >= 0), by Kintner's recurrence."""
    table: dict[tuple[int, int], np.ndarray] = {}
    rho2 = rho * rho
    for m in sorted({m for _, m in needed}):
        top = max(n for n, mm in needed if mm == m)
        r_m = rho**m
        table[(m, m)] = r_m
        if top >= m + 2:
            table[(m + 2, m)] = r_m * ((m + 2) * rho2 - (m + 1))
        for n in range(m + 4, top + 1, 2):
            k1 = (n + m) * (n - m) * (n - 2) / 2.0
            k2 = 2.0 * n * (n - 1) * (n - 2)
            k3 = -(m**2) * (n - 1) - n * (n - 1) * (n - 2)
            k4 = -n * (n + m - 2) * (n - m - 2) / 2.0
            table[(n, m)] = ((k2 * rho2 + k3) * table[(n - 2, m)] + k4 * table[(n - 4, m)]) / k1
    return table


def zernike_polar(rho: np.ndarray, theta: np.ndarray, n_terms: int = 400) -> np.ndarray:
    """Noll-normalised Zernike polynomials ``Z_1 ... Z_n_terms`` at polar points of the unit disk.

    Parameters
    ----------
    rho, theta : ndarray (n_points,)
        Radius (0 to 1) and angle (radians) of each point.
    n_terms : int
        Number of Noll indices, starting at 1.

    Returns
    -------
    ndarray (n_points, n_terms)
        Column ``j - 1`` holds ``Z_j``. NaN inputs give NaN rows.

    Examples
    --------
    >>> z = zernike_polar(np.array([0.5]), np.array([0.0]), 4)
    >>> np.round(z, 6).tolist()
    [[1.0, 1.0, 0.0, -0.866025]]
    """
    rho = check_array("rho", rho, ndim=1, dtype_kind="uif", allow_empty=True).astype(np.float64)
    theta = check_array("theta", theta, ndim=1, dtype_kind="uif", allow_empty=True)
    if theta.shape != rho.shape:
        raise ValueError(f"Expected `theta` to have shape {rho.shape}, got {theta.shape}.")
    if np.any(rho > 1.0 + 1e-12) or np.any(rho < 0.0):
        bad = rho[(rho > 1.0 + 1e-12) | (rho < 0.0)][0]
        raise ValueError(f"Expected `rho` within the unit disk [0, 1], got a value {bad!r}.")
    n, m = noll_to_nm(n_terms)
    am = np.abs(m)
    table = _radial_table(rho, set(zip(n.tolist(), am.tolist(), strict=True)))
    out = np.empty((n_terms, rho.size), dtype=np.float64)  # rows filled, returned transposed
    angular = {0: None}
    for k in range(1, int(am.max()) + 1):
        angular[k] = (np.cos(k * theta), np.sin(k * theta))
    for col, (nn, mm) in enumerate(zip(n.tolist(), m.tolist(), strict=True)):
        radial = table[(nn, abs(mm))]
        if mm == 0:
            np.multiply(np.sqrt(nn + 1.0), radial, out=out[col])
        else:
            trig = angular[abs(mm)][0 if mm > 0 else 1]
            np.multiply(radial, trig, out=out[col])
            out[col] *= np.sqrt(2.0 * (nn + 1.0))
    return out.T


def _check_field_shape(field_shape) -> tuple[int, int]:
    if not isinstance(field_shape, tuple | list) or len(field_shape) != 2:
        raise ValueError(f"Expected `field_shape` to be (H, W) in pixels, got {field_shape!r}.")
    h = check_int("field_shape[0]", field_shape[0], minimum=1)
    w = check_int("field_shape[1]", field_shape[1], minimum=1)
    return h, w


def field_to_disk(
    x_px: np.ndarray, y_px: np.ndarray, *, field_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Map image positions (pixels) into the unit disk that circumscribes the field.

    Parameters
    ----------
    x_px, y_px : ndarray (n_points,)
        Column and row positions in pixels. They must lie within the field including its pixel
        edges, ``-0.5 <= x <= W - 0.5`` and ``-0.5 <= y <= H - 0.5``; NaN passes through.
    field_shape : (int, int)
        ``(H, W)`` of the field in pixels.

    Returns
    -------
    rho, theta : ndarray (n_points,)
        Normalised radius and angle (radians, from +x towards +y).
    """
    h, w = _check_field_shape(field_shape)
    x = check_array("x_px", x_px, ndim=1, dtype_kind="uif", allow_empty=True).astype(np.float64)
    y = check_array("y_px", y_px, ndim=1, dtype_kind="uif", allow_empty=True).astype(np.float64)
    if x.shape != y.shape:
        raise ValueError(f"Expected `y_px` to have shape {x.shape}, got {y.shape}.")
    tol = 1e-9 * max(h, w)
    for name, v, top in (("x_px", x, w - 0.5), ("y_px", y, h - 0.5)):
        outside = (v < -0.5 - tol) | (v > top + tol)
        if np.any(outside):
            raise ValueError(
                f"Expected `{name}` within the field [-0.5, {top}] px, got {v[outside][0]!r}."
            )
    dx = x - (w - 1) / 2.0
    dy = y - (h - 1) / 2.0
    radius = np.hypot(w, h) / 2.0
    rho = np.minimum(np.hypot(dx, dy) / radius, 1.0)
    return rho, np.arctan2(dy, dx)


def zernike_design(
    x_px: np.ndarray, y_px: np.ndarray, *, field_shape: tuple[int, int], n_terms: int = 400
) -> np.ndarray:
    """Design matrix ``Z_j(x, y)`` (n_points, n_terms) of field positions in pixels.

    See :func:`field_to_disk` for the mapping and :func:`zernike_polar` for the polynomials.
    """
    rho, theta = field_to_disk(x_px, y_px, field_shape=field_shape)
    n_terms = check_int("n_terms", n_terms, minimum=1)
    out = np.empty((n_terms, rho.size))
    for start in range(0, rho.size, _CHUNK):
        block = slice(start, start + _CHUNK)
        out[:, block] = zernike_polar(rho[block], theta[block], n_terms).T
    return out.T


def lstsq_operator(design: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares operator ``pinv(design)`` from the thin SVD, and the condition number.

    ``coefficients = operator @ values`` is the least-squares solution for every column of
    ``values``, so one decomposition serves any number of columns that share ``design``.

    Returns
    -------
    operator : ndarray (n_terms, n_points)
    condition : float
        Ratio of the largest to the smallest singular value (``inf`` if rank-deficient).
    """
    u, s, vt = np.linalg.svd(design, full_matrices=False)
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    with np.errstate(divide="ignore"):
        inv = np.where(s > 0, 1.0 / s, 0.0)
    return (vt.T * inv) @ u.T, condition


def truncated_lstsq_operator(
    design: np.ndarray, *, max_terms: int, max_condition: float
) -> tuple[np.ndarray | None, float, int]:
    """Least-squares operator of the most leading columns of ``design`` that stay well conditioned.

    Finds the largest ``p <= max_terms`` such that ``design[:, :p]`` has a condition number of
    at most ``max_condition``. Adding a column never lowers the largest singular value nor raises
    the smallest (interlacing), so the condition number is non-decreasing in ``p`` and bisection
    finds ``p``. One QR factorisation serves every trial: ``design[:, :p] = Q[:, :p] R[:p, :p]``,
    so only the small triangular blocks ``R[:p, :p]`` are decomposed.

    Returns
    -------
    operator : ndarray (p, n_points) or None
        ``pinv(design[:, :p])``; None if not even one column qualifies.
    condition : float
        Condition number of ``design[:, :p]`` (NaN if ``p = 0``).
    p : int
    """
    p_max = min(int(max_terms), design.shape[1], design.shape[0])
    if p_max < 1:
        return None, float("nan"), 0
    q, r = np.linalg.qr(design[:, :p_max])
    u, s, vt = np.linalg.svd(r)
    p = p_max
    if not s[-1] > 0 or s[0] / s[-1] > max_condition:

        def acceptable(p: int) -> bool:
            sv = np.linalg.svd(r[:p, :p], compute_uv=False)
            return bool(sv[-1] > 0 and sv[0] / sv[-1] <= max_condition)

        good, bad = 0, p_max  # acceptable(good) (0: no term at all), not acceptable(bad)
        while bad - good > 1:
            mid = (good + bad) // 2
            good, bad = (mid, bad) if acceptable(mid) else (good, mid)
        p = good
        if p == 0:
            return None, float("nan"), 0
        u, s, vt = np.linalg.svd(r[:p, :p])
    return (vt.T / s) @ (q[:, :p] @ u).T, float(s[0] / s[-1]), p


def press_terms(design: np.ndarray, values: np.ndarray, *, max_terms: int) -> int:
    """Number of leading terms that minimises the leave-one-out (PRESS) error.

    Candidates are complete radial orders, ``p = (n + 1)(n + 2) / 2 <= max_terms``. For a least
    squares fit the leave-one-out residual has the closed form ``r_i / (1 - h_ii)``, with ``r``
    the fit residual and ``h_ii`` the leverage, the diagonal of the hat matrix
    ``Q_p Q_p^T`` (``design[:, :p] = Q_p R_p``), so one QR factorisation scores every candidate.
    The PRESS statistic is summed over the columns of ``values``.

    Parameters
    ----------
    design : ndarray (n_points, >= max_terms)
    values : ndarray (n_points, m)
    max_terms : int

    Returns
    -------
    int
        The best ``p`` (0 if no candidate has finite PRESS, e.g. fewer than 2 points).
    """
    p_max = min(int(max_terms), design.shape[1], design.shape[0])
    if p_max < 1:
        return 0
    q, _ = np.linalg.qr(design[:, :p_max])
    projections = q.T @ values
    resid = values.copy()
    leverage = np.zeros(design.shape[0])
    best, best_press, done, n = 0, np.inf, 0, 0
    while (p := (n + 1) * (n + 2) // 2) <= p_max:
        resid -= q[:, done:p] @ projections[done:p]
        leverage += np.sum(q[:, done:p] ** 2, axis=1)
        done, n = p, n + 1
        with np.errstate(divide="ignore", invalid="ignore"):
            press = float(np.sum((resid / (1.0 - leverage)[:, None]) ** 2))
        if np.isfinite(press) and np.all(leverage < 1.0 - 1e-9) and press < best_press:
            best, best_press = p, press
    return best


def fit_zernike(
    x_px: np.ndarray,
    y_px: np.ndarray,
    values: np.ndarray,
    *,
    field_shape: tuple[int, int],
    n_terms: int = 400,
    max_condition: float = 1e8,
) -> np.ndarray:
    """Least-squares Zernike coefficients of values sampled at field positions.

    Parameters
    ----------
    x_px, y_px : ndarray (n_points,)
        Sample positions in pixels.
    values : ndarray (n_points,) or (n_points, m)
        Values to fit; every column is fitted with the same design.
    field_shape : (int, int)
        ``(H, W)`` of the field, pixels.
    n_terms : int
        Noll indices ``1 ... n_terms``.
    max_condition : float
        Largest accepted condition number of the design matrix.

    Returns
    -------
    ndarray (n_terms,) or (n_terms, m)
        Coefficients, in the units of ``values``.

    Raises
    ------
    ValueError
        If there are fewer samples than terms or the design is worse conditioned than
        ``max_condition`` (use fewer terms or more samples).
    """
    design = zernike_design(x_px, y_px, field_shape=field_shape, n_terms=n_terms)
    values = check_array("values", values, ndim=(1, 2), dtype_kind="uif").astype(np.float64)
    if values.shape[0] != design.shape[0]:
        raise ValueError(
            f"Expected `values` to have {design.shape[0]} rows (one per point), got {values.shape}."
        )
    if not np.all(np.isfinite(values)):
        raise ValueError("Expected `values` to be finite.")
    max_condition = check_positive("max_condition", max_condition)
    if design.shape[0] < n_terms:
        raise ValueError(
            f"Expected at least `n_terms` = {n_terms} points to fit, got {design.shape[0]}."
        )
    operator, condition = lstsq_operator(design)
    if condition > max_condition:
        raise ValueError(
            f"The Zernike design is ill-conditioned (condition number {condition:.3g} > "
            f"`max_condition` = {max_condition:.3g}); use fewer terms or more points."
        )
    return operator @ values
