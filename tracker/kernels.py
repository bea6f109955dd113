"""The tracker's per-frame arithmetic as compiled kernels (numba), over arrays allocated once per tracker.

:class:`keyshape.tracker.fitting.Tracker` calls these for the work every frame repeats: the region models'
refinement and reading (:func:`refine_regions`), the pose polish's step (:func:`polish_step`), the global
reading (:func:`read_global`) and the lips' shape fit (:func:`lip_box`, then :func:`refine_write`).
Compiled on first use and cached on disk (``cache=True``; docs/tracker.md, "The per-frame step compiled").
Sums are reassociated for vectorisation (``fastmath`` ``reassoc``/``contract`` only: no assumptions about
NaN or infinities), so results differ from numpy's by rounding, and a kernel compiled in this process can
differ by a rounding (1e-14 px) from the same kernel loaded from the cache by a ``--jobs`` worker.
Divisions follow numpy's error model (no test for a zero divisor, which would stop the loops' vectorisation).

Conventions: images are ``uint8`` (row, column); affines ``(a00, a01, a02, a10, a11, a12)`` map a
patch pixel ``(x, y)`` to the image's ``(a00 x + a01 y + a02, a10 x + a11 y + a12)``, pixel centres
at integers (OpenCV's ``WARP_INVERSE_MAP``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_FM = {"reassoc", "contract"}
_JIT = {"cache": True, "nogil": True, "fastmath": _FM, "error_model": "numpy"}


@njit(**_JIT)
def sample_affine(img, a, out):
    """Bilinear samples of ``img`` at the affine ``a`` (6,) for every pixel of ``out`` (h, w), ``uint8``.

    The border is replicated (coordinates clipped into the image). The coordinates and the
    interpolation are evaluated in single precision with fused multiply-adds, as OpenCV 5's
    ``cv2.warpAffine(..., INTER_LINEAR | WARP_INVERSE_MAP, BORDER_REPLICATE)``: the grey levels
    are the same but for about one pixel in 50,000, one level apart. Coefficients that would
    place a corner of the patch beyond 1e7 pixels (or NaN, infinite) give a blank patch.
    """
    sh, sw = out.shape
    H, W = img.shape
    ok = True
    for i in range(6):
        if not (abs(a[i]) < 1e7):
            ok = False
    if ok:
        for cy in (-1.0, float(sh)):
            for cx in (-1.0, float(sw)):
                x = a[0] * cx + a[1] * cy + a[2]
                y = a[3] * cx + a[4] * cy + a[5]
                if not (abs(x) < 1e7 and abs(y) < 1e7):
                    ok = False
    if not ok:
        out[:] = 0
        return
    m0, m1, m2 = np.float32(a[0]), np.float32(a[1]), np.float32(a[2])
    m3, m4, m5 = np.float32(a[3]), np.float32(a[4]), np.float32(a[5])
    # inside: every sample and its right and lower neighbours lie in the image (no clipping needed)
    lo_x = hi_x = lo_y = hi_y = 0.0
    for cy in (0.0, float(sh - 1)):
        for cx in (0.0, float(sw - 1)):
            x = a[0] * cx + a[1] * cy + a[2]
            y = a[3] * cx + a[4] * cy + a[5]
            if cx == 0.0 and cy == 0.0:
                lo_x = hi_x = x
                lo_y = hi_y = y
            lo_x, hi_x, lo_y, hi_y = min(lo_x, x), max(hi_x, x), min(lo_y, y), max(hi_y, y)
    inside = lo_x >= 0.5 and lo_y >= 0.5 and hi_x < W - 2.5 and hi_y < H - 2.5
    for y in range(sh):
        fy = np.float32(y)
        bx = m1 * fy + m2
        by = m4 * fy + m5
        row = out[y]
        for x in range(sw):
            fx = np.float32(x)
            sx = m0 * fx + bx
            sy = m3 * fx + by
            if inside:
                ix = int(sx)
                iy = int(sy)
                x0 = ix
                x1 = ix + 1
                y0 = iy
                y1 = iy + 1
            else:
                ix = int(math.floor(sx))
                iy = int(math.floor(sy))
                x0 = min(max(ix, 0), W - 1)
                x1 = min(max(ix + 1, 0), W - 1)
                y0 = min(max(iy, 0), H - 1)
                y1 = min(max(iy + 1, 0), H - 1)
            ax = sx - np.float32(ix)
            ay = sy - np.float32(iy)
            # unsigned indices: no wrap-around test for negative ones (they are clipped or inside)
            ux0, ux1, uy0, uy1 = np.uint64(x0), np.uint64(x1), np.uint64(y0), np.uint64(y1)
            p00 = np.float32(img[uy0, ux0])
            p10 = np.float32(img[uy1, ux0])
            v0 = ax * (np.float32(img[uy0, ux1]) - p00) + p00
            v1 = ax * (np.float32(img[uy1, ux1]) - p10) + p10
            row[x] = np.uint8(np.rint(ay * (v1 - v0) + v0))


@njit(**_JIT)
def _gradients(img, h, w, gx, gy):
    """3x3 Sobel gradients (unscaled, as ``cv2.spatialGradient``) of the flat ``h`` x ``w`` image ``img`` into
    the flat ``gx``, ``gy``; the border mirrored without repeating the edge (OpenCV's default, ``-1 -> 1``)."""
    for y in range(h):
        ym = (y - 1 if y > 0 else min(1, h - 1)) * w
        yp = (y + 1 if y < h - 1 else max(h - 2, 0)) * w
        yc = y * w
        rm, rc, rp = img[ym:ym + w], img[yc:yc + w], img[yp:yp + w]
        ox, oy = gx[yc + 1:yc + w], gy[yc + 1:yc + w]
        for x in range(w - 2):               # the row's inside (x + 1): a plain stencil, exact in int32
            a = np.int32(rm[x])
            c = np.int32(rm[x + 2])
            g = np.int32(rp[x])
            k = np.int32(rp[x + 2])
            ox[x] = np.float64((c - a) + 2 * (np.int32(rc[x + 2]) - np.int32(rc[x])) + (k - g))
            oy[x] = np.float64((g - a) + 2 * (np.int32(rp[x + 1]) - np.int32(rm[x + 1])) + (k - c))
        for x in (0, w - 1):
            if x == w - 1 and w == 1:
                continue
            xm = x - 1 if x > 0 else min(1, w - 1)
            xp = x + 1 if x < w - 1 else max(w - 2, 0)
            a, c = np.float64(img[ym + xm]), np.float64(img[ym + xp])
            g, k = np.float64(img[yp + xm]), np.float64(img[yp + xp])
            gx[yc + x] = (c - a) + 2.0 * (np.float64(img[yc + xp]) - np.float64(img[yc + xm])) + (k - g)
            gy[yc + x] = (g - a) + 2.0 * (np.float64(img[yp + x]) - np.float64(img[ym + x])) + (k - c)


@njit(**_JIT)
def _normalised_error(img, index, mean, e):
    """``e = (v - μ)/σ - mean`` of the pixels ``index`` of the flat image ``img``; returns ``(σ, |e|²)``."""
    n = index.size
    sv = 0.0
    for i in range(n):
        v = np.float64(img[np.uint64(index[i])])
        e[i] = v
        sv += v
    mu = sv / n
    e0 = 0.0
    for i in range(n):
        d = e[i] - mu
        e0 += d * d
    sd = max(math.sqrt(max(e0, 0.0) / n), 1e-6)
    s = 1.0 / sd
    ee = 0.0
    for i in range(n):
        v = (e[i] - mu) * s - mean[i]
        e[i] = v
        ee += v * v
    return sd, ee


@njit(**_JIT)
def _project(qt, e, n, q, qe):
    """``qe = Qᵀe`` over the first ``q`` rows and ``n`` columns of ``qt``; returns ``|Qᵀe|²``."""
    qq = 0.0
    for a in range(q):
        acc = 0.0
        for i in range(n):
            acc += qt[a, i] * e[i]
        qe[a] = acc
        qq += acc * acc
    return qq


@njit(**_JIT)
def _scaled_gradients(gxy, idx, k, ga, gb):
    """``ga``, ``gb``: the gradients ``gxy`` (2, flat) at the pixels ``idx``, times ``k``."""
    for i in range(idx.size):
        kk = np.uint64(idx[i])
        ga[i] = gxy[0, kk] * k
        gb[i] = gxy[1, kk] * k


@njit(**_JIT)
def _cholesky_solve(h, g, npar, sol):
    """``sol = -h⁻¹ g`` by Cholesky (``h`` npar x npar, overwritten), as ``cv2.solve(..., DECOMP_CHOLESKY)``:
    False where a pivot falls under machine epsilon (not positive definite)."""
    for i in range(npar):
        for j in range(i):
            s = h[i, j]
            for k in range(j):
                s -= h[i, k] * h[j, k]
            h[i, j] = s * h[j, j]
        s = h[i, i]
        for k in range(i):
            s -= h[i, k] * h[i, k]
        if s < 2.220446049250313e-16:
            return False
        h[i, i] = 1.0 / math.sqrt(s)
    for i in range(npar):                      # L y = -g (h's diagonal holds 1/L_ii)
        s = -g[i]
        for k in range(i):
            s -= h[i, k] * sol[k]
        sol[i] = s * h[i, i]
    for i in range(npar - 1, -1, -1):          # Lᵀ x = y
        s = sol[i]
        for k in range(i + 1, npar):
            s -= h[k, i] * sol[k]
        sol[i] = s * h[i, i]
    return True


@njit(**_JIT)
def _box_normal_equations(gxy, idx, k, xc, stretch, qt, q, e, qe, jac, qj, at, shared, hess, grad):
    """Add one box's projected-out normal equations to a group's (``hess``, ``grad``): its translation's
    rows and columns at ``at``, ``at + 1``, the shared stretch and tilt (``stretch``) at ``shared``,
    ``shared + 1``. ``gxy`` the box's Sobel gradients (flat), ``k = 1/(8σ)``, ``xc`` each pixel's x from the
    box centre, ``qt`` its basis (``q`` rows), ``e`` and ``qe`` its error and ``Qᵀe``."""
    n = idx.size
    ga, gb = jac[0], jac[1]
    _scaled_gradients(gxy, idx, k, ga, gb)
    p = 4 if stretch else 2
    for a in range(q):                          # QᵀJ: a pass over the pixels per basis row
        s0 = s1 = s2 = s3 = 0.0
        if stretch:
            for i in range(n):
                qa = qt[a, i]
                qx = qa * xc[i]
                s0 += qa * ga[i]
                s1 += qa * gb[i]
                s2 += qx * ga[i]
                s3 += qx * gb[i]
        else:
            for i in range(n):
                qa = qt[a, i]
                s0 += qa * ga[i]
                s1 += qa * gb[i]
        qj[a, 0], qj[a, 1], qj[a, 2], qj[a, 3] = s0, s1, s2, s3
    # JJᵀ and Je in one pass (rows x, y, and with the stretch x xc, y xc)
    h00 = h01 = h02 = h03 = h11 = h12 = h13 = h22 = h23 = h33 = 0.0
    e0 = e1 = e2 = e3 = 0.0
    if stretch:
        for i in range(n):
            j0, j1 = ga[i], gb[i]
            c = xc[i]
            j2, j3 = j0 * c, j1 * c
            ei = e[i]
            h00 += j0 * j0
            h01 += j0 * j1
            h02 += j0 * j2
            h03 += j0 * j3
            h11 += j1 * j1
            h12 += j1 * j2
            h13 += j1 * j3
            h22 += j2 * j2
            h23 += j2 * j3
            h33 += j3 * j3
            e0 += j0 * ei
            e1 += j1 * ei
            e2 += j2 * ei
            e3 += j3 * ei
    else:
        for i in range(n):
            j0, j1 = ga[i], gb[i]
            ei = e[i]
            h00 += j0 * j0
            h01 += j0 * j1
            h11 += j1 * j1
            e0 += j0 * ei
            e1 += j1 * ei
    jj = ((h00, h01, h02, h03), (h01, h11, h12, h13), (h02, h12, h22, h23), (h03, h13, h23, h33))
    je = (e0, e1, e2, e3)
    for j in range(p):
        rj = at + j if j < 2 else shared + j - 2
        acc = je[j]
        for a in range(q):
            acc -= qj[a, j] * qe[a]
        grad[rj] += acc
        for l in range(p):
            rl = at + l if l < 2 else shared + l - 2
            acc = jj[j][l]
            for a in range(q):
                acc -= qj[a, j] * qj[a, l]
            hess[rj, rl] += acc


@njit(**_JIT)
def refine_regions(img, f, pose, patch, tables, work):
    """Refine and read region models' boxes in the model frame: Gauss-Newton on each group's summed
    distance from its regions' appearance subspaces, then the eigen-points at the best motion.

    A group (``groups[g] = (first, last, steps, stretch)``: regions ``first:last`` of the tables) is a
    region alone (its box translates, ``t = (t_x, t_y)``) or the lips (``stretch`` 1: each box its own
    translation, all one horizontal stretch ``s`` and tilt ``k`` about the box centre ``c``, a box
    pixel ``b`` going to ``corner + b + t + (s (b_x - c_x), k (b_x - c_x))``). For region ``r`` with
    normalised error ``e`` (``(v - μ)/σ - m``, its ``n`` pixels), basis ``Q`` and Jacobian rows
    ``J = G/(8σ)`` (``G`` the 3x3 Sobel gradients in x and y of the box, and for the lips each times
    ``b_x - c_x``), the projected-out normal equations are ``H = JJᵀ - (QᵀJᵀ)ᵀQᵀJᵀ`` and
    ``g = Je - (QᵀJᵀ)ᵀQᵀe``; the lips add each box's block at its translation and the shared pair.
    At most ``steps`` steps, each ``-H⁻¹g`` (``+1e-6`` on the diagonal) with translations clipped
    to 2 px a step and ``|t| <= lims[0]``, ``|s|, |k| <= lims[1]``, kept only while the distance
    ``Σ |e|² - |Qᵀe|²`` falls. The first evaluation reads the boxes from ``patch`` (the global
    model-frame patch at ``pose``, ``image_from_model`` (6,)), later ones sample ``img`` (the pyramid
    level of scale ``f = 0.5 ** level``) at ``pose ∘ box motion``.

    ``tables`` is ``(groups, geo, box_cx, index, mean_i, xc, qt, coef, inv_var, mean_l, ul, lims)``, ``work``
    ``(crop, gxy, e, jac, qj, qe, best_qe, hess, grad, sol, t, pts)``.
    Tables (regions in order, padded): ``geo`` (r, 6) box ``x0, y0, w, h``, ``n`` pixels and ``q`` basis rows, ``box_cx``
    (r,) the box centre's x from its corner; ``index`` (r, n) flat pixel indices in the box; ``mean_i``, ``xc``
    (r, n); ``qt`` (r, q, n); ``coef`` (r, c, q) = ``pinv_i Q`` (coefficients from ``Qᵀe``);
    ``inv_var`` (r, c) (0 past a region's own); ``mean_l`` (r, 2p), ``ul`` (r, 2p, c) landmark rows.
    Work arrays: ``crop`` (h w,) ``uint8`` and ``gxy`` (2, h w) for a box and its gradients,
    ``e`` (n,), ``jac`` (4, n), ``qj`` (q, 4), ``qe``/``best_qe`` (r, q), ``hess`` (8, 8) and ``grad``/``sol``
    (8,) (up to 3 lips). Outputs: ``t`` (r, 4) each box's ``t_x, t_y, s, k``; ``pts`` (r, p, 2) each region's
    points in the model frame (zero past its own). Returns the largest ``mean c²/λ``.
    """
    groups, geo, box_cx, index, mean_i, xc, qt, coef, inv_var, mean_l, ul, lims = tables
    crop, gxy, e, jac, qj, qe, best_qe, hess, grad, sol, t, pts = work
    a00, a01, a02, a10, a11, a12 = pose[0], pose[1], pose[2], pose[3], pose[4], pose[5]
    d = 0.5 * f - 0.5                 # the level's pixel centres: x_l = f x_0 + 0.5 f - 0.5
    lim, slim = lims[0], lims[1]
    m2 = 0.0
    sub = np.empty(6)
    cvec = np.empty(coef.shape[1])
    for gi in range(groups.shape[0]):
        first, last_r, steps, stretch = groups[gi, 0], groups[gi, 1], groups[gi, 2], groups[gi, 3]
        nm = last_r - first
        npar = 2 * nm + (2 if stretch else 0)
        for r in range(first, last_r):
            t[r, 0] = t[r, 1] = t[r, 2] = t[r, 3] = 0.0
        st = kt = 0.0
        best_r = np.inf
        bst = bkt = 0.0
        for it in range(steps + 1):
            grad_on = it < steps
            for i in range(npar):
                grad[i] = 0.0
                for j in range(npar):
                    hess[i, j] = 0.0
            dist = 0.0
            for mi in range(nm):
                r = first + mi
                x0, y0, w, h, ni, q = geo[r, 0], geo[r, 1], geo[r, 2], geo[r, 3], geo[r, 4], geo[r, 5]
                cx = box_cx[r]
                flat = crop[:h * w]
                box = flat.reshape((h, w))
                if it == 0:
                    for yy in range(h):
                        for xx in range(w):
                            flat[yy * w + xx] = patch[y0 + yy, x0 + xx]
                else:
                    # image_from_box = pose ∘ [[1 + s, 0, x0 + t_x - s c_x], [k, 1, y0 + t_y - k c_x]], at the level
                    bx = x0 + t[r, 0] - st * cx
                    by = y0 + t[r, 1] - kt * cx
                    sub[0] = (a00 * (1.0 + st) + a01 * kt) * f
                    sub[1] = a01 * f
                    sub[2] = (a00 * bx + a01 * by + a02) * f + d
                    sub[3] = (a10 * (1.0 + st) + a11 * kt) * f
                    sub[4] = a11 * f
                    sub[5] = (a10 * bx + a11 * by + a12) * f + d
                    sample_affine(img, sub, box)
                idx = index[r, :ni]
                sd, ee = _normalised_error(flat, idx, mean_i[r], e)
                qq = _project(qt[r], e, ni, q, qe[r])
                dist += ee - qq
                if not grad_on:
                    continue
                k = 1.0 / (8.0 * sd)
                _gradients(flat, h, w, gxy[0], gxy[1])
                _box_normal_equations(gxy, idx, k, xc[r], stretch, qt[r], q, e, qe[r], jac, qj, 2 * mi, 2 * nm,
                                      hess, grad)
            if dist >= best_r:
                break
            best_r = dist
            for mi in range(nm):
                r = first + mi
                for a in range(qe.shape[1]):
                    best_qe[r, a] = qe[r, a]
                t[r, 2] = t[r, 0]             # the best translation so far, kept in t[:, 2:] meanwhile
                t[r, 3] = t[r, 1]
            bst, bkt = st, kt
            if not grad_on:
                break
            for i in range(npar):
                hess[i, i] += 1e-6
            if not stretch:
                h00, h01, h11 = hess[0, 0], hess[0, 1], hess[1, 1]
                g0, g1 = grad[0], grad[1]
                det = h00 * h11 - h01 * h01
                if det <= 0:
                    break
                sol[0] = -(h11 * g0 - h01 * g1) / det
                sol[1] = -(h00 * g1 - h01 * g0) / det
            elif not _cholesky_solve(hess, grad, npar, sol):
                break
            for mi in range(nm):
                r = first + mi
                t[r, 0] = max(-lim, min(lim, t[r, 0] + max(-2.0, min(2.0, sol[2 * mi]))))
                t[r, 1] = max(-lim, min(lim, t[r, 1] + max(-2.0, min(2.0, sol[2 * mi + 1]))))
            if stretch:
                st = max(-slim, min(slim, st + sol[npar - 2]))
                kt = max(-slim, min(slim, kt + sol[npar - 1]))
        # read each region at the group's best motion
        for mi in range(nm):
            r = first + mi
            tx, ty = t[r, 2], t[r, 3]
            t[r, 0], t[r, 1], t[r, 2], t[r, 3] = tx, ty, bst, bkt
            nc = coef.shape[1]
            c_m2 = 0.0
            n_c = 0
            pts_n = mean_l.shape[1] // 2
            for ci in range(nc):
                acc = 0.0
                for a in range(qe.shape[1]):
                    acc += coef[r, ci, a] * best_qe[r, a]
                cvec[ci] = acc
                if inv_var[r, ci] > 0:
                    c_m2 += acc * acc * inv_var[r, ci]
                    n_c += 1
            if n_c:
                m2 = max(m2, c_m2 / n_c)
            x0, cx = geo[r, 0], box_cx[r]
            for pi in range(pts_n):
                px = mean_l[r, 2 * pi]
                py = mean_l[r, 2 * pi + 1]
                for ci in range(nc):
                    px += ul[r, 2 * pi, ci] * cvec[ci]
                    py += ul[r, 2 * pi + 1, ci] * cvec[ci]
                bx = px - (x0 + cx)
                pts[r, pi, 0] = px + tx + bst * bx
                pts[r, pi, 1] = py + ty + bkt * bx
    return m2


@njit(**_JIT)
def polish_step(patch, level, work):
    """One forward-compositional Gauss-Newton evaluation of the pose polish at a model-frame ``patch``.

    ``e`` the normalised error against ``template`` at the pixels ``index``, ``Qᵀe`` (``qt`` the
    level's projection basis, rows), the distance ``|e|² - |Qᵀe|²`` per pixel; the Jacobian rows of the
    six affine parameters ``(gx x, gy x, gx y, gy y, gx, gy)/(8σ)`` (3x3 Sobel gradients of the patch
    at pixel ``(x, y)``), and the step ``sol = (J⊥ᵀJ⊥)⁻¹ (QᵀJ)ᵀQᵀe - Jᵀe`` with ``J⊥ᵀJ⊥ = JᵀJ - (QᵀJ)ᵀQᵀJ``
    (``1e-9`` on the diagonal, Gaussian elimination with partial pivoting). Returns ``(distance, ok)``;
    ``ok`` False where the system is singular. ``level`` is ``(index, qt, template, xx, yy)`` (the pixels'
    flat indices in the patch and their x, y), ``work`` ``(gxy, e, jac, qe, qj, hess, rhs, sol)``, ``sol``
    the step.
    """
    index, qt, template, xx, yy = level
    gxy, e, jac, qe, qj, hess, rhs, sol = work
    n = index.size
    h, w = patch.shape
    flat = patch.reshape(h * w)
    sd, ee = _normalised_error(flat, index, template, e)
    qq = _project(qt, e, n, qt.shape[0], qe)
    r = max(ee - qq, 0.0) / n
    k = 1.0 / (8.0 * sd)
    _gradients(flat, h, w, gxy[0], gxy[1])
    ga, gb = jac[0], jac[1]
    _scaled_gradients(gxy, index, k, ga, gb)
    # QᵀJ, a pass over the pixels per basis row
    nq = qt.shape[0]
    for a in range(nq):
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for i in range(n):
            qa = qt[a, i]
            qx = qa * xx[i]
            qy = qa * yy[i]
            s0 += qx * ga[i]
            s1 += qx * gb[i]
            s2 += qy * ga[i]
            s3 += qy * gb[i]
            s4 += qa * ga[i]
            s5 += qa * gb[i]
        qj[a, 0], qj[a, 1], qj[a, 2], qj[a, 3], qj[a, 4], qj[a, 5] = s0, s1, s2, s3, s4, s5
    # JᵀJ (upper triangle) and Jᵀe in one pass
    h00 = h01 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = 0.0
    h22 = h23 = h24 = h25 = h33 = h34 = h35 = h44 = h45 = h55 = 0.0
    e0 = e1 = e2 = e3 = e4 = e5 = 0.0
    for i in range(n):
        j4, j5 = ga[i], gb[i]
        x, y = xx[i], yy[i]
        j0, j1, j2, j3 = j4 * x, j5 * x, j4 * y, j5 * y
        h00 += j0 * j0
        h01 += j0 * j1
        h02 += j0 * j2
        h03 += j0 * j3
        h04 += j0 * j4
        h05 += j0 * j5
        h11 += j1 * j1
        h12 += j1 * j2
        h13 += j1 * j3
        h14 += j1 * j4
        h15 += j1 * j5
        h22 += j2 * j2
        h23 += j2 * j3
        h24 += j2 * j4
        h25 += j2 * j5
        h33 += j3 * j3
        h34 += j3 * j4
        h35 += j3 * j5
        h44 += j4 * j4
        h45 += j4 * j5
        h55 += j5 * j5
        ei = e[i]
        e0 += j0 * ei
        e1 += j1 * ei
        e2 += j2 * ei
        e3 += j3 * ei
        e4 += j4 * ei
        e5 += j5 * ei
    hess[0, 0], hess[0, 1], hess[0, 2], hess[0, 3], hess[0, 4], hess[0, 5] = h00, h01, h02, h03, h04, h05
    hess[1, 1], hess[1, 2], hess[1, 3], hess[1, 4], hess[1, 5] = h11, h12, h13, h14, h15
    hess[2, 2], hess[2, 3], hess[2, 4], hess[2, 5] = h22, h23, h24, h25
    hess[3, 3], hess[3, 4], hess[3, 5] = h33, h34, h35
    hess[4, 4], hess[4, 5], hess[5, 5] = h44, h45, h55
    rhs[0], rhs[1], rhs[2], rhs[3], rhs[4], rhs[5] = e0, e1, e2, e3, e4, e5
    # projected out: J⊥ᵀJ⊥ = JᵀJ - (QᵀJ)ᵀQᵀJ, and the right-hand side -J⊥ᵀe⊥ = (QᵀJ)ᵀQᵀe - Jᵀe
    for j in range(6):
        acc = rhs[j]
        for a in range(nq):
            acc -= qj[a, j] * qe[a]
        rhs[j] = -acc
        for l in range(j, 6):
            acc = hess[j, l]
            for a in range(nq):
                acc -= qj[a, j] * qj[a, l]
            hess[j, l] = acc
            hess[l, j] = acc
        hess[j, j] += 1e-9
    # Gaussian elimination with partial pivoting (hess and rhs overwritten)
    for c in range(6):
        piv = c
        for i in range(c + 1, 6):
            if abs(hess[i, c]) > abs(hess[piv, c]):
                piv = i
        if abs(hess[piv, c]) < 2.220446049250313e-14:      # as cv2.solve(..., DECOMP_LU): 100 epsilon
            return r, False
        if piv != c:
            for j in range(6):
                hess[c, j], hess[piv, j] = hess[piv, j], hess[c, j]
            rhs[c], rhs[piv] = rhs[piv], rhs[c]
        for i in range(c + 1, 6):
            fct = hess[i, c] / hess[c, c]
            for j in range(c, 6):
                hess[i, j] -= fct * hess[c, j]
            rhs[i] -= fct * rhs[c]
    for i in range(5, -1, -1):
        acc = rhs[i]
        for j in range(i + 1, 6):
            acc -= hess[i, j] * sol[j]
        sol[i] = acc / hess[i, i]
    return r, True


@njit(**_JIT)
def read_global(patch, reading, work):
    """The global eigen-points reading of a model-frame ``patch``: coefficients ``c = pinv_I e`` of the
    normalised error ``e`` (``mean_i`` the mean appearance), landmarks ``shape`` (flat, ``mean_l + basis c``
    with ``basis`` (2 n_points, k)) and ``(residual, σ, mean c²/λ)``, the residual ``|e - U_I c|²/n``
    expanded as ``(|e|² - 2 cᵀU_Iᵀe + cᵀ(U_IᵀU_I)c)/n``. ``pinv`` (2k, n) stacks ``pinv_I`` over ``U_Iᵀ``;
    ``gram`` is ``U_IᵀU_I``, ``inv_var`` (k,) the components' ``1/λ``. ``reading`` is ``(index, mean_i, pinv,
    gram, basis, mean_l, inv_var)``, ``work`` ``(e, c, shape)``."""
    index, mean_i, pinv, gram, basis, mean_l, inv_var = reading
    e, c, shape = work
    n = index.size
    k = c.size
    sd, ee = _normalised_error(patch.reshape(patch.size), index, mean_i, e)
    cu = np.empty(2 * k)
    _project(pinv, e, n, 2 * k, cu)
    cue = 0.0
    m2 = 0.0
    for a in range(k):
        c[a] = cu[a]
        cue += cu[a] * cu[k + a]
        m2 += cu[a] * cu[a] * inv_var[a]
    npt = shape.size
    cgc = 0.0
    for a in range(k):
        acc = 0.0
        for b in range(k):
            acc += gram[a, b] * c[b]
        cgc += c[a] * acc
    for j in range(npt):
        acc = mean_l[j]
        for a in range(k):
            acc += basis[j, a] * c[a]
        shape[j] = acc
    return max(ee - 2.0 * cue + cgc, 0.0) / n, sd, m2 / k


#: the border (pixels, replicated) of the images :func:`sample_shape` samples
PAD = 4


@njit(**_JIT)
def _bilinear(img, x, y):
    """The bilinear sample of ``img`` at ``(x, y)`` (pixel centres at integers), ``x`` and ``y`` at least 0 and
    under the last column and row (no test: the caller clamps)."""
    ix = int(x)
    iy = int(y)
    ax = x - ix
    ay = y - iy
    # unsigned indices: no wrap-around test for negative ones
    x0, x1, y0, y1 = np.uint64(ix), np.uint64(ix + 1), np.uint64(iy), np.uint64(iy + 1)
    p00 = img[y0, x0]
    p10 = img[y1, x0]
    v0 = p00 + ax * (img[y0, x1] - p00)
    v1 = p10 + ax * (img[y1, x1] - p10)
    return v0 + ay * (v1 - v0)


@njit(**_JIT)
def _bilinear_grad(img, x, y):
    """The bilinear sample ``b(x, y)`` of ``img[0]`` and its differences half a pixel either side,
    ``b(x + 1/2, y) - b(x - 1/2, y)`` and ``b(x, y + 1/2) - b(x, y - 1/2)``, ``img`` a :func:`padded` stack
    (``PAD`` pixels of replicated border around the image sampled): a difference of two bilinear samples a
    pixel apart is the bilinear sample of the pixels' differences (``img[1]``, ``img[2]``) half a pixel back.
    Samples beyond the image take its border's values (each coordinate clamped to 1.5 pixels beyond the
    border, where the five samples all read the replicated border)."""
    H, W = img.shape[1], img.shape[2]
    x = min(max(x, PAD - 1.5), W - PAD + 0.5)
    y = min(max(y, PAD - 1.5), H - PAD + 0.5)
    return _bilinear(img[0], x, y), _bilinear(img[1], x - 0.5, y), _bilinear(img[2], x, y - 0.5)


@njit(**_JIT)
def padded(crop):
    """``crop`` as float64 with ``PAD`` pixels of replicated border (the images :func:`sample_shape` samples),
    stacked with its differences to the next column and to the next row (0 past the last): (3, h + 2 PAD,
    w + 2 PAD)."""
    h, w = crop.shape
    H, W = h + 2 * PAD, w + 2 * PAD
    out = np.empty((3, H, W))
    img, dx, dy = out[0], out[1], out[2]
    for r in range(H):
        src = crop[min(max(r - PAD, 0), h - 1)]
        row = img[r]
        for c in range(w):
            row[c + PAD] = src[c]
        for c in range(PAD):
            row[c] = src[0]
            row[w + PAD + c] = src[w - 1]
        drow = dx[r]
        for c in range(W - 1):
            drow[c] = row[c + 1] - row[c]
        drow[W - 1] = 0.0
    for r in range(H - 1):
        a, b, drow = img[r], img[r + 1], dy[r]
        for c in range(W):
            drow[c] = b[c] - a[c]
    for c in range(W):
        dy[H - 1, c] = 0.0
    return out


@njit(**_JIT)
def sample_shape(img, f, pose, template, s, out):
    """Grey levels ``v`` (n_pix,) of a shape-normalised template, ``template = (tri, bary, ext)``, and the
    image's gradients at them (central differences half a pixel either side): template pixel ``i`` lies in
    the triangle ``tri[i]`` of the vertices ``ext s`` (``ext`` (n_vertices, m) maps the shape's ``m`` points
    ``s``, flat ``(x0, y0, x1, ...)``, to the triangulation's vertices) at the barycentric weights
    ``bary[i]``, in the model frame; ``pose`` (6,) maps it to the image and ``f`` to pyramid level ``img``
    (``x_l = f x + f/2 - 1/2``; ``img`` the :func:`padded` stack of the level's pixels, ``pose`` mapping to
    its pixels). ``out = (vx, v, gx, gy)``: ``vx`` (n_vertices, 2) receives the vertices at the level,
    ``v``, ``gx``, ``gy`` (distinct arrays) the samples and gradients."""
    tri, bary, ext = template
    vx, v, gx, gy = out
    nv, m = ext.shape
    a0, a1, a2, a3, a4, a5 = pose[0], pose[1], pose[2], pose[3], pose[4], pose[5]
    d = 0.5 * f - 0.5
    for r in range(nv):                              # the vertices, mapped to the level (the map is affine)
        ax = 0.0
        ay = 0.0
        for j in range(m):
            ax += ext[r, j] * s[2 * j]
            ay += ext[r, j] * s[2 * j + 1]
        vx[r, 0] = f * (a0 * ax + a1 * ay + a2) + d
        vx[r, 1] = f * (a3 * ax + a4 * ay + a5) + d
    for i in range(tri.shape[0]):
        t0, t1, t2 = np.uint64(tri[i, 0]), np.uint64(tri[i, 1]), np.uint64(tri[i, 2])
        b0, b1, b2 = bary[i, 0], bary[i, 1], bary[i, 2]
        x = b0 * vx[t0, 0] + b1 * vx[t1, 0] + b2 * vx[t2, 0]
        y = b0 * vx[t0, 1] + b1 * vx[t1, 1] + b2 * vx[t2, 1]
        v[i], gx[i], gy[i] = _bilinear_grad(img, x, y)


@njit(**_JIT)
def refine_shape(img, f, pose, s, tables, work, n_iter):
    """Fit a region's shape to the frame by analysis by synthesis (a project-out active appearance model,
    forward additive Gauss-Newton): the shape ``s`` (flat model-frame points, updated in place) moves in its
    subspace ``s0 + S p`` so that the normalised grey levels of its shape-normalised template
    (:func:`sample_shape`) match the mean appearance ``a0`` up to the appearance basis (projected out
    with ``qt``, which holds the ones too), under the Gaussian prior ``w p²`` (``w`` the pixel noise over
    each shape component's variance). ``tables`` = ``(tri, bary, ext, gsx, gsy, sb, s0, a0, qt, w)``: the
    template of :func:`sample_shape`, ``gsx = (G S_x)ᵀ``, ``gsy = (G S_y)ᵀ`` (k, n_pix; ``G`` the pixels' weights
    of the shape's points), ``sb`` the basis ``S`` (2m, k). ``work`` = ``(vx, v, gx, gy, e, jac, qe, qj,
    hess, grad, p, dp)``, ``jac`` (k, n_pix). At most ``n_iter`` steps, until no parameter moves by 1e-3. Returns the steps."""
    tri, bary, ext, gsx, gsy, sb, s0, a0, qt, w = tables
    vx, v, gx, gy, e, jac, qe, qj, hess, grad, p, dp = work
    k, n = gsx.shape
    q = qt.shape[0]
    for c in range(k):                               # the start's parameters (the rest of s is kept)
        acc = 0.0
        for r in range(s.shape[0]):
            acc += sb[r, c] * (s[r] - s0[r])
        p[c] = acc
    a0x, a1x, a3x, a4x = pose[0] * f, pose[1] * f, pose[3] * f, pose[4] * f
    steps = 0
    for _ in range(n_iter):
        sample_shape(img, f, pose, (tri, bary, ext), s, (vx, v, gx, gy))
        mu = 0.0
        for i in range(n):
            mu += v[i]
        mu /= n
        var = 0.0
        for i in range(n):
            var += (v[i] - mu) * (v[i] - mu)
        sd = max(math.sqrt(var / n), 1e-6)
        inv = 1.0 / sd
        for i in range(n):
            e[i] = (v[i] - mu) * inv - a0[i]
            jx = (gx[i] * a0x + gy[i] * a3x) * inv
            jy = (gx[i] * a1x + gy[i] * a4x) * inv
            gx[i] = jx
            gy[i] = jy
        for c in range(k):
            for i in range(n):
                jac[c, i] = gx[i] * gsx[c, i] + gy[i] * gsy[c, i]
        _project(qt, e, n, q, qe)
        for a in range(q):
            for c in range(k):
                acc = 0.0
                for i in range(n):
                    acc += qt[a, i] * jac[c, i]
                qj[a, c] = acc
        for c in range(k):
            acc = 0.0
            for i in range(n):
                acc += jac[c, i] * e[i]
            for a in range(q):
                acc -= qj[a, c] * qe[a]
            grad[c] = acc + w[c] * p[c]
            for c2 in range(c + 1):
                acc = 0.0
                for i in range(n):
                    acc += jac[c, i] * jac[c2, i]
                for a in range(q):
                    acc -= qj[a, c] * qj[a, c2]
                hess[c, c2] = acc
                hess[c2, c] = acc
            hess[c, c] += w[c]
        if not _cholesky_solve(hess, grad, k, dp):
            break
        big = 0.0
        for c in range(k):
            p[c] += dp[c]
            big = max(big, abs(dp[c]))
        for r in range(s.shape[0]):
            acc = 0.0
            for c in range(k):
                acc += sb[r, c] * dp[c]
            s[r] += acc
        steps += 1
        if big < 1e-3:
            break
    return steps


@njit(**_JIT)
def shape_box(pose, s, f, size, box):
    """The crop a shape near ``s`` (flat model-frame points) is fitted on: the box (``box`` (4,) int, ``x0, y0,
    x1, y1``) of level ``f`` (of ``size = (height, width)``) around the points mapped by ``pose`` ((2, 3)
    ``image_from_model``), 60% of their extent and 4 pixels beyond, at least 2 x 2 pixels inside the level.
    Returns False (``box`` unset) where a point is not finite."""
    h, w = size[0], size[1]
    d = 0.5 * f - 0.5
    lx = ly = math.inf
    hx = hy = -math.inf
    for j in range(s.shape[0] // 2):
        x = (s[2 * j] * pose[0, 0] + s[2 * j + 1] * pose[0, 1] + pose[0, 2]) * f + d
        y = (s[2 * j] * pose[1, 0] + s[2 * j + 1] * pose[1, 1] + pose[1, 2]) * f + d
        lx, hx, ly, hy = min(lx, x), max(hx, x), min(ly, y), max(hy, y)
    pad = 0.6 * max(hx - lx, hy - ly) + 4.0
    if not (math.isfinite(lx) and math.isfinite(hx) and math.isfinite(ly) and math.isfinite(hy) and pad < 1e6):
        return False
    box[0] = min(max(math.floor(lx - pad), 0), w - 2)
    box[1] = min(max(math.floor(ly - pad), 0), h - 2)
    box[2] = max(min(math.ceil(hx + pad), w), box[0] + 2)
    box[3] = max(min(math.ceil(hy + pad), h), box[1] + 2)
    return True


@njit(**_JIT)
def lip_box(pose, points, idx, f, size, s, box):
    """``s`` (flat, 2 len(idx)) the model-frame positions of the image points ``points[idx]`` under ``pose``
    ((2, 3) ``image_from_model``), and their crop (:func:`shape_box`). Returns :func:`shape_box`'s flag."""
    det = pose[0, 0] * pose[1, 1] - pose[0, 1] * pose[1, 0]
    i00, i01, i10, i11 = pose[1, 1] / det, -pose[0, 1] / det, -pose[1, 0] / det, pose[0, 0] / det
    for j in range(idx.shape[0]):
        x = points[idx[j], 0] - pose[0, 2]
        y = points[idx[j], 1] - pose[1, 2]
        s[2 * j] = i00 * x + i01 * y
        s[2 * j + 1] = i10 * x + i11 * y
    return shape_box(pose, s, f, size, box)


@njit(**_JIT)
def refine_write(crop, f, pose, box, s, tables, work, n_iter, where, points):
    """:func:`refine_shape` on ``crop`` (level ``f``'s pixels from ``box``'s corner, :func:`lip_box`, with
    :func:`padded`'s border) from the shape ``s``, then the fitted points ``s[at]`` mapped by ``pose`` into ``points[write]`` (image pixels),
    ``where = (at, write)``. Returns the steps."""
    at, write = where
    a = np.empty(6)
    a[0], a[1], a[2] = pose[0, 0], pose[0, 1], pose[0, 2] - (box[0] - PAD) / f
    a[3], a[4], a[5] = pose[1, 0], pose[1, 1], pose[1, 2] - (box[1] - PAD) / f
    steps = refine_shape(crop, f, a, s, tables, work, n_iter)
    for j in range(at.shape[0]):
        x, y = s[2 * at[j]], s[2 * at[j] + 1]
        points[write[j], 0] = pose[0, 0] * x + pose[0, 1] * y + pose[0, 2]
        points[write[j], 1] = pose[1, 0] * x + pose[1, 1] * y + pose[1, 2]
    return steps
