"""BPDN on a small working set, written with its Gram matrix: ``|b - D x|^2 + lam |x|_1`` as
``bb + x^H G x - 2 Re c^H x + lam |x|_1`` (``G = D^H D``, ``c = D^H b``, ``bb = |b|^2``).

:func:`fista_gram` runs FISTA with restart and, where its certified gap is not yet reached,
polishes with :func:`newton_polish`: Newton's method on the smooth problem that the support
defines. FISTA alone needs thousands of steps on a coherent grid (neighbouring atoms half a
sample apart make ``G`` ill-conditioned); the support is found in a few hundred, and Newton
then converges in a few steps.

Amplitude models: ``"positive"``, ``"real"``, ``"complex"`` (|x_i| the modulus) and
``"pairs"`` (real ``x = [Re, Im]`` stacked, |x_i| the modulus of each pair: the working sets of
:class:`clsas.sparse.bpdn.RealPartOperator`).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["POLISH", "fista_gram", "newton_polish"]

#: The default of :func:`fista_gram`'s ``polish``; the benchmarks set it False to time FISTA alone.
POLISH = True


def atom_magnitudes(z, amplitudes):
    """Per-atom magnitudes; ``"pairs"``: ``z`` holds ``[Re x, Im x]`` stacked (real)."""
    if amplitudes == "pairs":
        k = len(z) // 2
        return np.hypot(z[:k], z[k:])
    return np.abs(z)


def _prox(z, t, amplitudes):
    if amplitudes == "pairs":
        k = len(z) // 2
        p = _prox(z[:k] + 1j * z[k:], t, "complex")
        return np.r_[p.real, p.imag]
    if amplitudes == "positive":
        return np.maximum(z.real - t, 0.0)
    if amplitudes == "real":
        return np.sign(z.real) * np.maximum(np.abs(z.real) - t, 0.0)
    mag = np.abs(z)
    return np.where(mag > t, (1 - t / np.maximum(mag, 1e-300)) * z, 0.0)


def as_pairs(G, c, x):
    """The complex problem as a real one in ``[Re x, Im x]``: ``x^H G x = u^T G2 u``."""
    G2 = np.block([[G.real, -G.imag], [G.imag, G.real]])
    return G2, np.r_[c.real, c.imag], np.r_[x.real, x.imag]


def newton_polish(G, c, lam, x, amplitudes, max_steps: int = 30):
    """Newton's method on the support of ``x`` (its nonzero atoms, their phases free): the
    objective is smooth there, its Hessian ``2 G`` plus ``lam (I - n n^T) / |x_i|`` on each
    atom (curvature along the phase only). An atom whose modulus a step drives through zero
    leaves the support at that point; a backtracking line search keeps every step downhill,
    so ``x`` returns with an objective no higher than it came with.
    ``amplitudes``: ``"complex"`` or ``"pairs"``. Returns the polished ``x`` (same layout)."""
    if amplitudes == "complex":
        G2, c2, u = as_pairs(G, c, x)
        u = _newton_pairs(G2, c2, lam, u, max_steps)
        k = len(x)
        return u[:k] + 1j * u[k:]
    if amplitudes == "pairs":
        return _newton_pairs(G, c, lam, np.array(x, float), max_steps)
    raise ValueError(f"amplitudes must be 'complex' or 'pairs' for newton_polish, got {amplitudes!r}")


def _newton_direction(Gs, cs, us, lam) -> tuple[np.ndarray, float] | None:
    """The Newton step of ``z Gs z - 2 cs z + lam sum |z_g|`` at ``us`` (pairs layout, every group
    nonzero) and the objective's slope along it; None where it does not descend."""
    n = len(us) // 2
    j = np.arange(n)
    mm = np.hypot(us[:n], us[n:])
    n1, n2 = us[:n] / mm, us[n:] / mm
    grad = 2 * (Gs @ us) - 2 * cs + lam * np.r_[n1, n2]
    H = 2 * Gs
    H[j, j] += lam * n2**2 / mm  # lam (I - n n^T) / |u_g|: curvature along the phase only
    H[j + n, j + n] += lam * n1**2 / mm
    H[j, j + n] -= lam * n1 * n2 / mm
    H[j + n, j] -= lam * n1 * n2 / mm
    try:
        d = np.linalg.solve(H, -grad)
    except np.linalg.LinAlgError:
        d = np.linalg.lstsq(H, -grad, rcond=None)[0]
    slope = float(grad @ d)
    if not np.all(np.isfinite(d)) or slope >= 0:
        return None
    return d, slope


def _line_search_to_zero(f, us, fu, d, slope) -> tuple[np.ndarray, float, int | None] | None:
    """A backtracking (Armijo) step from ``us`` along ``d``: ``(point, f there, the group set to zero
    or None)``, or None where 40 halvings find no decrease.

    An atom whose modulus the step drives through zero leaves the support there (as in
    feature-sign search): the step is first shortened to that point and the atom set to zero."""
    n = len(us) // 2
    mm = np.hypot(us[:n], us[n:])
    radial = us[:n] / mm * d[:n] + us[n:] / mm * d[n:]  # the step along each group's modulus
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = np.where(radial < 0, -mm / radial, np.inf)
    hit = int(np.argmin(cross))
    t = float(min(cross[hit], 1.0))
    for _ in range(40):
        trial = us + t * d
        zeroed = t == cross[hit]
        if zeroed:
            trial[[hit, hit + n]] = 0.0
        ft = f(trial)
        if ft <= fu + 1e-4 * t * slope:
            return trial, ft, (hit if zeroed else None)
        t /= 2
    return None


def _newton_pairs(G2, c2, lam, u, max_steps):
    """Newton on the support of ``u`` (pairs layout), the matrices cut to the support once per
    support; an atom that a step drives through zero is removed and the matrices cut again."""
    k = len(u) // 2
    u = np.array(u, float)
    m = np.hypot(u[:k], u[k:])
    on = np.flatnonzero(m > 1e-12 * max(m.max(initial=0.0), 1e-300))
    off = np.setdiff1d(np.arange(k), on)
    u[off], u[off + k] = 0.0, 0.0  # below rounding of the largest: the caller keeps the better point
    steps = 0
    while on.size and steps < max_steps:
        n, idx = on.size, np.r_[on, on + k]
        Gs, cs, us = G2[np.ix_(idx, idx)], c2[idx], u[idx]

        def f(z, Gs=Gs, cs=cs, n=n):
            return float(z @ Gs @ z - 2 * cs @ z + lam * np.hypot(z[:n], z[n:]).sum())

        fu, left = f(us), None
        while steps < max_steps:
            steps += 1
            step = _newton_direction(Gs, cs, us, lam)
            found = None if step is None else _line_search_to_zero(f, us, fu, *step)
            if found is None:
                break
            trial, ft, zeroed = found
            done = fu - ft <= 1e-15 * max(abs(fu), 1e-300)
            us, fu = trial, ft
            if zeroed is not None:
                left = zeroed
                break
            if done:
                break
        u[idx] = us
        if left is None:
            break
        on = np.delete(on, left)
    return u


def fista_gram(G, c, bb, lam, amplitudes, x, tol, max_iter, deadline=np.inf, polish: bool | None = None):
    """FISTA with restart on the working set's problem, with a Newton polish on the support at
    each check that the gap is not reached; stops at a restricted duality gap <= tol x the
    objective. ``polish=False``: FISTA alone (default :data:`POLISH`). Returns ``(x, iterations)``
    (FISTA steps)."""
    polish = POLISH if polish is None else bool(polish)
    dtype = x.dtype
    L = 2 * max(np.linalg.eigvalsh(G)[-1], 1e-300)
    step = 1.0 / L
    lp = lam / 2

    def f(z):
        return float(bb + np.vdot(z, G @ z).real - 2 * np.vdot(c, z).real + lam * atom_magnitudes(z, amplitudes).sum())

    def gap(z):
        g = c - G @ z  # D^H r
        dn = np.max(g.real) if amplitudes == "positive" else np.max(atom_magnitudes(g, amplitudes))
        s = 1.0 if dn <= lp else lp / dn
        xgx, cx = np.vdot(z, G @ z).real, np.vdot(c, z).real
        rr = bb - 2 * cx + xgx
        b_minus_theta = (1 - s) ** 2 * bb + 2 * s * (1 - s) * cx + s**2 * xgx
        return max(0.0, rr + lam * atom_magnitudes(z, amplitudes).sum() - (bb - b_minus_theta))

    y, t_mom, f_prev = x.copy(), 1.0, f(x)
    it = 0
    for it in range(1, max_iter + 1):
        x_new = _prox(y - 2 * step * (G @ y - c), lam * step, amplitudes).astype(dtype)
        f_new = f(x_new)
        if f_new > f_prev:
            y, t_mom = x.copy(), 1.0
            continue
        t_next = 0.5 * (1 + np.sqrt(1 + 4 * t_mom**2))
        y = x_new + ((t_mom - 1) / t_next) * (x_new - x)
        x, f_prev, t_mom = x_new, f_new, t_next
        if it % 25:
            continue
        if gap(x) <= tol * max(f_prev, 1e-300) or time.perf_counter() > deadline:
            break
        if polish and it % 50 == 0 and amplitudes in ("complex", "pairs"):  # the support has settled: solve on it
            xp = newton_polish(G, c, lam, x, amplitudes).astype(dtype)
            fp = f(xp)
            if fp < f_prev:
                x, y, f_prev, t_mom = xp, xp.copy(), fp, 1.0
                if gap(x) <= tol * max(f_prev, 1e-300):
                    break
    return x, it
