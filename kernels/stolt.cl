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
 * clsas/formation/stolt_numpy.py:spread. Needs common.cl (RINT, sincos_2pi, the lane unions).
 *
 * The VEC columns of a work-item are its vector lanes: everything per sample (kz, window,
 * strength, position) and per kernel tap (the weight) is computed for the VEC columns at once,
 * with operators rather than builtins (common.cl's note), and only the read-modify-write of a
 * cell goes lane by lane. The tap weight exp(beta (sqrt(1 - x^2) - 1)) uses exp_neg below. */

/* exp(y) for y in [-126 ln 2, 0]: 2^n 2^f, n = rint(y log2 e), f in [-0.5, 0.5]; 2^f by its
 * Taylor polynomial of degree 6 in f ln 2 (relative error < 2e-7), 2^n from the bits. */
inline floatV exp_neg(const floatV y)
{
    floatV t = y * 1.44269504089f;
    t = t < -126.0f ? (floatV)(-126.0f) : t;
    const floatV n = RINT(t);
    const floatV x = (t - n) * 0.69314718056f;
    const floatV p = 1.0f + x * (1.0f + x * (0.5f + x * (1.0f / 6.0f + x * (1.0f / 24.0f
                   + x * (1.0f / 120.0f + x * (1.0f / 720.0f))))));
    /* n + 127 in [1, 127] sits in the low mantissa bits of n + (2^23 + 127) */
    const intV e = (as_intV(n + 8388735.0f) & 0xff) << 23;
    return p * as_floatV(e);
}



/* One frequency sample k of VEC columns (|k_perp|^2 = kp2, |k_perp| = kp, (b . k_perp)^2 = proj2):
 * the lanes the sample reaches (-1: kz real and the look angle under s2), kz (k's sign), the
 * bistatic alpha and the strength's amplitude w 2 pi k / kz^2 (w: the look-angle window). Lanes
 * not reached get a finite kz (1); alpha is infinite where k = 0, which no caller keeps. */
inline intV stolt_sample(const float kk, const floatV kp2, const floatV kp, const floatV proj2, const float b2,
                         const float4 win, const float s2, floatV *kz, floatV *alpha, floatV *amp)
{
    const floatV kz2 = kk * kk - kp2;
    const floatV s = kp * fabs(1.0f / kk);
    const floatV kz_abs = sqrt(kz2 > 0.0f ? kz2 : (floatV)(1.0f));
    *kz = kk < 0.0f ? -kz_abs : kz_abs;   /* negative frequencies: kz < 0 */
    const floatV ramp = (s - win.z) * win.w;
    floatV wc;
    sincos_2pi(0.5f * (ramp > 1.0f ? (floatV)(1.0f) : ramp), &wc);   /* cos(pi ramp) */
    const floatV w = ramp <= 0.0f ? (floatV)(1.0f) : 0.5f * (1.0f + wc);
    *alpha = 0.125f * *kz * (b2 - proj2 * (1.0f / (kk * kk)));
    *amp = w * (6.28318530718f * kk) / (kz_abs * kz_abs);
    return (kz2 > 0.0f) & (s < s2);
}



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
    const float inv_hw = 1.0f / hw;
    const float fm = (float)n_cells, inv_m = 1.0f / (float)n_cells;
    lanes_f kx, ky;
    lanes_i live;                             /* -1 for a real column, 0 for padding */
    for (int l = 0; l < VEC; ++l) {
        const int col = c_first + l;
        live.s[l] = col < n_cols ? -1 : 0;
        const float2 kp = kuv[col < n_cols ? col : n_cols - 1];
        kx.s[l] = kp.x;
        ky.s[l] = kp.y;
        if (col < n_cols)
            for (int p = 0; p < n_terms; ++p)
                for (int m = 0; m < n_cells; ++m)
                    cells[((size_t)p * n_cols + col) * n_cells + m] = (float2)(0.0f, 0.0f);
    }
    const floatV kp2 = kx.v * kx.v + ky.v * ky.v;
    const floatV kp = sqrt(kp2);
    const floatV proj = win.x * kx.v + win.y * ky.v;
    const floatV proj2 = proj * proj;
    for (int j = 0; j < n_f; ++j) {
        const float kk = k[j];
        floatV kz, alpha, amp;
        lanes_i ok;
        ok.v = live.v & stolt_sample(kk, kp2, kp, proj2, b2, win, s2, &kz, &alpha, &amp);
        floatV cyc = kz * geo.y + alpha * geo.w;
        cyc -= RINT(cyc);
        floatV ph_c;
        const floatV ph_s = sincos_2pi(cyc, &ph_c);
        const floatV q = geo.z / kz;                      /* the 1 / (kz zref) term */
        lanes_f dr, di;
        for (int l = 0; l < VEC; ++l) {
            const float2 d = ok.s[l] ? spec[(size_t)(c_first + l) * n_f + j] : (float2)(0.0f, 0.0f);
            dr.s[l] = d.x;
            di.s[l] = d.y;
        }
        /* d * amp * (1 + i q) * (ph_c + i ph_s) */
        const floatV ar = amp * (ph_c - q * ph_s), ai = amp * (ph_s + q * ph_c);
        const floatV c0r = dr.v * ar - di.v * ai, c0i = dr.v * ai + di.v * ar;
        const floatV pos = kz * geo.x;
        floatV first = RINT(pos - hw);
        first = first < pos - hw ? first + 1.0f : first;   /* ceil */
        for (int t = 0; t < width; ++t) {
            const floatV cell = first + (float)t;
            const floatV x = (cell - pos) * inv_hw;
            const floatV arg = 1.0f - x * x;
            const floatV phi = arg > 0.0f ? exp_neg(beta * (sqrt(arg > 0.0f ? arg : (floatV)(0.0f)) - 1.0f))
                                          : (floatV)(0.0f);
            /* the cell modulo M, from floats (|cell| < 2^22) */
            floatV fold = RINT(cell * inv_m);
            fold = fold * fm > cell ? fold - 1.0f : fold;
            lanes_f idx, vr, vi, al;
            idx.v = cell - fold * fm;
            al.v = alpha;
            vr.v = phi * c0r;
            vi.v = phi * c0i;
            for (int l = 0; l < VEC; ++l) {
                if (!ok.s[l]) continue;
                int ci = (int)idx.s[l];
                ci = ci >= n_cells ? ci - n_cells : (ci < 0 ? ci + n_cells : ci);
                                float2 v = (float2)(vr.s[l], vi.s[l]);
                for (int p = 0; p < n_terms; ++p) {
                    cells[((size_t)p * n_cols + c_first + l) * n_cells + ci] += v;
                    v *= al.s[l];
                }
            }
        }
    }
}


/* The Stolt sum evaluated directly at the output depths (no spreading, no FFT):
 *
 *   out[col, l] = sum_p fac[p, l] sum_j c0_j alpha_j^p exp(i kz_j l' dz),   l' = l - n_z / 2
 *
 * with c0_j, alpha_j as in stolt_spread (c0 carries exp(i kz zc + i alpha / zref), so the phase
 * is kz z at depth z = zc + l' dz). It is what the spread, the inverse FFT and the de-apodisation
 * approximate, exactly: for few frequency samples and depths (n_f n_z small against the cells'
 * FFT) it is the cheaper of the two. fac[p, l] are the bistatic expansion's weights (i u_z)^p / p!
 * times whatever per-depth factor the caller folds in. NumPy twin: clsas/formation/stolt_numpy.py:direct.
 *
 * Work-item: VEC consecutive columns (its lanes), all depths. The inputs come lanes contiguous
 * (the host pads the columns to whole items with zeros), so every load is one vector; the sums
 * build up in the item's own slice of acc (n_z re/im vector pairs) and are copied to out at the end. Per sample the
 * strength and the step exp(i kz dz) are formed once; the depths follow by complex rotations,
 * restarted from an exact sincos every ZR depths (float32 rotation error: about 1e-7 a step). */
#define ZR 32

__kernel void stolt_depths(
    __global const floatV *spec_r,   /* (n_f, items) data spectrum, real parts, VEC columns each   */
    __global const floatV *spec_i,   /* (n_f, items) ... imaginary parts (weights applied)       */
    __global const float *k,         /* (n_f,) two-way wavenumber 4 pi f / c, rad/m (any sign)  */
    __global const floatV *ku,       /* (items,) column spatial frequencies, rad/m (padding: 0)  */
    __global const floatV *kv,       /* (items,) ...                                            */
    const int n_cols,                /* columns (the last item's lanes past it are padding)     */
    const int n_f,                   /* frequency samples per column                            */
    const float4 geo,                /* (dz / 2 pi [m / rad], zc / 2 pi [m / rad], 1 / zref [1/m],
                                        1 / (2 pi zref) [1/(m rad)])                            */
    const float4 win,                /* (bu, bv) baseline, m; s1; 1 / (s2 - s1)                 */
    const float s2,                  /* look-angle sine where the window reaches zero           */
    const int n_z,                   /* output depths                                           */
    const int n_terms,               /* powers of alpha                                         */
    __global const float2 *fac,      /* (n_terms, n_z) per-depth weight of each power           */
    __global floatV *acc,            /* (items, n_z, 2) scratch                                 */
    __global float2 *out)            /* (n_cols, n_z) output                                    */
{
    const int item = get_global_id(0), n_items = get_global_size(0);
    const int c_first = item * VEC;
    __global floatV *a = acc + (size_t)item * n_z * 2;
    const float b2 = win.x * win.x + win.y * win.y;
    const float h = (float)(n_z / 2);
    const floatV kx = ku[item], ky = kv[item];
    for (int z = 0; z < 2 * n_z; ++z)
        a[z] = (floatV)(0.0f);
    const floatV kp2 = kx * kx + ky * ky;
    const floatV kp = sqrt(kp2);
    const floatV proj = win.x * kx + win.y * ky;
    const floatV proj2 = proj * proj;
    for (int j = 0; j < n_f; ++j) {
        const float kk = k[j];
        floatV kz, alpha_all, amp;
        const intV ok = stolt_sample(kk, kp2, kp, proj2, b2, win, s2, &kz, &alpha_all, &amp);
        /* samples not kept carry zeros (k = 0 would give infinities) */
        const floatV alpha = ok ? alpha_all : (floatV)(0.0f);
        floatV c1 = kz * geo.y + alpha * geo.w;   /* phase at zc, cycles */
        c1 -= RINT(c1);
        floatV st = kz * geo.x;                   /* the step exp(i kz dz), cycles */
        st -= RINT(st);
        floatV st_c;
        const floatV st_s = sincos_2pi(st, &st_c);
        const floatV q = geo.z / kz;
        const floatV dr = spec_r[(size_t)j * n_items + item], di = spec_i[(size_t)j * n_items + item];
        /* d amp (1 + i q): the strength without its phase */
        const floatV ur = ok ? amp * (dr - q * di) : (floatV)(0.0f);
        const floatV ui = ok ? amp * (di + q * dr) : (floatV)(0.0f);
        for (int z0 = 0; z0 < n_z; z0 += ZR) {
            /* exact phase at depth z0: c1 + kz (z0 - h) dz / 2 pi, reduced in two parts */
            floatV c2 = kz * (((float)z0 - h) * geo.x);
            c2 -= RINT(c2);
            floatV cyc = c1 + c2;
            cyc -= RINT(cyc);
            floatV ph_c;
            const floatV ph_s = sincos_2pi(cyc, &ph_c);
            floatV vr = ur * ph_c - ui * ph_s, vi = ur * ph_s + ui * ph_c;
            const int z1 = z0 + ZR < n_z ? z0 + ZR : n_z;
            for (int z = z0; z < z1; ++z) {
                /* g = sum_p fac[p, z] alpha^p (Horner) */
                float2 f = fac[(n_terms - 1) * n_z + z];
                floatV gr = (floatV)(f.x), gi = (floatV)(f.y);
                for (int p = n_terms - 2; p >= 0; --p) {
                    f = fac[p * n_z + z];
                    gr = gr * alpha + f.x;
                    gi = gi * alpha + f.y;
                }
                a[2 * z] += vr * gr - vi * gi;
                a[2 * z + 1] += vr * gi + vi * gr;
                const floatV nr = vr * st_c - vi * st_s;
                vi = vr * st_s + vi * st_c;
                vr = nr;
            }
        }
    }
    /* the sums back lane by lane; the lane loop unrolled (constant lane indices: Oclgrind's
     * uninitialised-value check loses track of a union's lane read at a variable index) */
    for (int z = 0; z < n_z; ++z) {
        lanes_f r, i;
        r.v = a[2 * z];
        i.v = a[2 * z + 1];
        #pragma unroll
        for (int l = 0; l < VEC; ++l)
            if (c_first + l < n_cols)
                out[(size_t)(c_first + l) * n_z + z] = (float2)(r.s[l], i.s[l]);
    }
}
