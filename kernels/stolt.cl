/* Stolt mapping and spreading of the wavenumber-domain (omega-k) formation.
 *
 * One spatial-frequency column (ku, kv) per loop iteration; each work-item owns VEC
 * consecutive columns and writes only their cells (no atomics, no races). For every frequency
 * sample j of a column (two-way wavenumber k_j):
 *   kz    = sign(k_j) sqrt(k_j^2 - ku^2 - kv^2)                 (skipped where k_j^2 <= ku^2 + kv^2)
 *   s     = |k_perp| / |k_j|;  w = 1 below s1, raised cosine to 0 at s2  (look-angle window)
 *   alpha = kz / 8 (|b|^2 - (b . k_perp)^2 / k_j^2)               (bistatic correction, rad m)
 *   c0    = spec_j w 2 pi k_j / kz^2 (1 + i / (kz zref)) exp(i (kz zc + alpha / zref))
 *   pos   = kz dz M / (2 pi)                                      (position on the kz axis, cells)
 * and c0 alpha^p is added, for each term p, to the W cells around pos (modulo M) with the
 * weight exp(beta (sqrt(1 - (2 x / W)^2) - 1)), x the cell's distance from pos.
 * The phase is reduced to cycles in [-0.5, 0.5] before sin/cos. NumPy twin:
 * clsas/formation/stolt.py:spread. Needs common.cl (RINT). */

__kernel void stolt_spread(
    __global const float2 *spec,     /* (n_cols, n_f) data spectrum, weights applied            */
    __global const float *k,         /* (n_f,) two-way wavenumber 4 pi f / c, rad/m (any sign)  */
    __global const float2 *kuv,      /* (n_cols,) column spatial frequencies (ku, kv), rad/m     */
    const int n_cols,                /* columns                                                 */
    const int n_f,                   /* frequency samples per column                            */
    const float4 geo,                /* (dz M / 2 pi [cells per rad/m], zc / 2 pi [m / rad],
                                        1 / zref [1/m], 1 / (2 pi zref) [1/(m rad)])            */
    const float4 win,                /* (bu, bv) baseline, m; s1; 1 / (s2 - s1)                 */
    const float s2,                  /* look-angle sine where the window reaches zero           */
    const int n_cells,               /* M: cells of the folded kz axis                          */
    const int width,                 /* W: kernel width, cells                                  */
    const float beta,                /* kernel shape                                            */
    const int n_terms,               /* powers of alpha spread                                  */
    __global float2 *cells)          /* (n_terms, n_cols, n_cells) output                       */
{
    const int c_first = get_global_id(0) * VEC;
    const float b2 = win.x * win.x + win.y * win.y;
    const float hw = 0.5f * (float)width;     /* half the kernel width, cells */
    for (int l = 0; l < VEC; ++l) {
        const int col = c_first + l;
        if (col >= n_cols) break;
        for (int p = 0; p < n_terms; ++p)
            for (int m = 0; m < n_cells; ++m)
                cells[((size_t)p * n_cols + col) * n_cells + m] = (float2)(0.0f, 0.0f);
        const float2 kp = kuv[col];
        const float kp2 = kp.x * kp.x + kp.y * kp.y;
        const float proj = win.x * kp.x + win.y * kp.y;
        for (int j = 0; j < n_f; ++j) {
            const float kk = k[j];
            const float kz2 = kk * kk - kp2;
            if (kz2 <= 0.0f) continue;
            const float s = sqrt(kp2) / fabs(kk);
            if (s >= s2) continue;
            const float ramp = (s - win.z) * win.w;
            const float w = ramp <= 0.0f ? 1.0f : 0.5f * (1.0f + cospi(ramp));
            const float kz = copysign(sqrt(kz2), kk);    /* negative frequencies: kz < 0 */
            const float alpha = 0.125f * kz * (b2 - proj * proj / (kk * kk));
            float cyc = kz * geo.y + alpha * geo.w;
            cyc -= RINT(cyc);
            const float ph_c = cospi(2.0f * cyc), ph_s = sinpi(2.0f * cyc);
            const float amp = w * 6.28318530718f * kk / kz2;
            const float q = geo.z / kz;                      /* the 1 / (kz zref) term */
            const float2 d = spec[(size_t)col * n_f + j];
            /* d * amp * (1 + i q) * (ph_c + i ph_s) */
            const float ar = amp * (ph_c - q * ph_s), ai = amp * (ph_s + q * ph_c);
            const float2 c0 = (float2)(d.x * ar - d.y * ai, d.x * ai + d.y * ar);
            const float pos = kz * geo.x;
            const float first = ceil(pos - hw);
            for (int t = 0; t < width; ++t) {
                const float cell = first + (float)t;
                const float x = (cell - pos) / hw;
                const float arg = 1.0f - x * x;
                if (arg <= 0.0f) continue;
                const float phi = exp(beta * (sqrt(arg) - 1.0f));
                const int ci = (int)cell;
                const int idx = ci - n_cells * (int)floor((float)ci / (float)n_cells);
                float2 v = phi * c0;
                for (int p = 0; p < n_terms; ++p) {
                    cells[((size_t)p * n_cols + col) * n_cells + idx] += v;
                    v *= alpha;
                }
            }
        }
    }
}
