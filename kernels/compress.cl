/* Pulse compression kernels: matched filter and FMCW dechirp, both giving complex baseband
 * range profiles over a gated window of delays.
 *
 * A profile value at delay tau is the analytic correlation rotated to baseband:
 *   P(tau) = exp(-j 2 pi fc tau) * sum_n x[tau*fs + n] conj(s_a[n]),
 * so backprojection restores the carrier with exp(+j 2 pi fc tau).
 *
 * Needs common.cl. Each work-item computes VEC consecutive lags of one measurement.
 * Rows of `out` are `out_stride` (a multiple of VEC) long; lags past n_lags are padding. */

__kernel void matched_filter(
    __global const float *signals,   /* (n_meas, n_samples) recordings, arbitrary units      */
    const int n_samples,             /* samples per recording                               */
    __global const float2 *ref,      /* (n_ref,) conj of the analytic transmit waveform     */
    const int n_ref,                 /* reference length, samples                           */
    const int lag0,                  /* lag of profile sample 0, samples into the recording */
    const int lag_step,              /* lag step between profile samples (decimation D)     */
    const int n_lags,                /* lags wanted per measurement                         */
    __global const float2 *rot,      /* (out_stride,) exp(-j 2 pi fc D k / fs), k = 0..     */
    __global const float2 *rot0,     /* (n_meas,) exp(-j 2 pi fc (t0_m + lag0 / fs))        */
    const int out_stride,            /* row length of out (multiple of VEC)                 */
    __global float2 *out)            /* (n_meas, out_stride) baseband profiles              */
{
    const int blk = get_global_id(0);
    const int m = get_global_id(1);
    const int k0 = blk * VEC;               /* first profile sample of this work-item */
    if (k0 >= out_stride) return;
    const int L = lag0 + k0 * lag_step;     /* first lag, samples */
    __global const float *row = signals + (size_t)m * n_samples;

    floatV acc_re = (floatV)(0.0f);
    floatV acc_im = (floatV)(0.0f);
    if (L >= 0 && L + (VEC - 1) * lag_step + n_ref - 1 < n_samples) {
        /* fast path: the whole window lies inside the recording */
        __global const float *x = row + L;
        for (int n = 0; n < n_ref; ++n) {
            lanes_f xv;
            for (int l = 0; l < VEC; ++l) xv.s[l] = x[n + l * lag_step];
            const float2 r = ref[n];
            acc_re += xv.v * r.x;
            acc_im += xv.v * r.y;
        }
    } else {
        /* edge path: samples outside the recording contribute nothing */
        float re[VEC], im[VEC];
        for (int l = 0; l < VEC; ++l) {
            float sr = 0.0f, si = 0.0f;
            const int lag = L + l * lag_step;
            const int n_lo = max(0, -lag);
            const int n_hi = min(n_ref, n_samples - lag);
            for (int n = n_lo; n < n_hi; ++n) {
                const float x = row[lag + n];
                sr += x * ref[n].x;
                si += x * ref[n].y;
            }
            re[l] = sr;
            im[l] = si;
        }
        lanes_f ure, uim;
        for (int l = 0; l < VEC; ++l) { ure.s[l] = re[l]; uim.s[l] = im[l]; }
        acc_re = ure.v;
        acc_im = uim.v;
    }

    /* rotate to baseband: exp(-j 2 pi fc (t0 + (lag0 + D k)/fs)) = rot0[m] * rot[k] */
    lanes_f ore, oim;
    ore.v = acc_re;
    oim.v = acc_im;
    const float2 r0 = rot0[m];
    __global float2 *o = out + (size_t)m * out_stride + k0;
    for (int l = 0; l < VEC; ++l) {
        const float2 rk = rot[k0 + l];
        const float2 w = (float2)(r0.x * rk.x - r0.y * rk.y, r0.x * rk.y + r0.y * rk.x);
        const float2 v = (float2)(ore.s[l] * w.x - oim.s[l] * w.y, ore.s[l] * w.y + oim.s[l] * w.x);
        o[l] = (k0 + l < n_lags) ? v : (float2)(0.0f);
    }
}

__kernel void fmcw_dechirp(
    __global const float *signals,   /* (n_meas, n_samples) recordings                          */
    const int n_samples,             /* samples per recording                                   */
    __global const float2 *ref,      /* (n_ref,) conj(s_a[n]) * window[n]: dechirp reference    */
    const int n_ref,                 /* samples mixed, from recording sample 0 (common t0)      */
    const float beat_cycles_per_sample_per_s, /* chirp slope / fs: beat cycles per sample per s */
    const float tau0_s,              /* delay of profile sample 0 after the transmit start, s  */
    const float dtau_s,              /* profile delay step, s                                   */
    const int n_lags,                /* delays wanted                                           */
    __global const float2 *rvp,      /* (out_stride,) residual-video-phase and baseband rotation */
    const int out_stride,            /* row length of out (multiple of VEC)                     */
    __global float2 *out)            /* (n_meas, out_stride) baseband profiles                  */
{
    /* Dechirp d[n] = x[n] conj(s_a[n]) w[n] is a tone at -k tau for an echo at delay tau;
     * evaluate its DFT at the gated beat frequencies (the low-pass is implicit: only beat
     * frequencies inside the gate are computed, the 2 fc mixing product falls outside). */
    const int blk = get_global_id(0);
    const int m = get_global_id(1);
    const int k0 = blk * VEC;
    if (k0 >= out_stride) return;
    __global const float *row = signals + (size_t)m * n_samples;
    lanes_f tl;
    for (int l = 0; l < VEC; ++l) tl.s[l] = tau0_s + (float)(k0 + l) * dtau_s;
    const floatV tau = tl.v;
    /* phase step per sample (cycles) for each delay; centred time keeps phases small */
    const floatV step = tau * beat_cycles_per_sample_per_s;
    const int n_mix = min(n_ref, n_samples);
    const float centre = 0.5f * (float)(n_mix - 1);
    floatV acc_re = (floatV)(0.0f);
    floatV acc_im = (floatV)(0.0f);
    for (int n = 0; n < n_mix; ++n) {
        const float x = row[n];
        const float2 r = ref[n];
        const float dre = x * r.x, dim = x * r.y;
        floatV cyc = step * ((float)n - centre);
        cyc -= RINT(cyc);
        floatV c;
        const floatV s = sincos_2pi(cyc, &c);
        acc_re += dre * c - dim * s;
        acc_im += dre * s + dim * c;
    }
    lanes_f ore, oim;
    ore.v = acc_re;
    oim.v = acc_im;
    __global float2 *o = out + (size_t)m * out_stride + k0;
    for (int l = 0; l < VEC; ++l) {
        const float2 w = rvp[k0 + l];
        const float2 v = (float2)(ore.s[l] * w.x - oim.s[l] * w.y, ore.s[l] * w.y + oim.s[l] * w.x);
        o[l] = (k0 + l < n_lags) ? v : (float2)(0.0f);
    }
}

/* ---- matched filter by FFT, decimated in the frequency domain ----------------------------
 *
 * The same profile as matched_filter (lag step D), computed as
 *   X = FFT_N(slice of the recording, zero-padded to N)
 *   Y[j] = X[bin0 + j] * spec[j]          j = -N'/2 .. N'/2 - 1 (baseband bins), N' = N / D
 *   c = IFFT_N'(Y)                         the correlation at lags 0, D, 2D, ... (circular)
 *   P[k] = rot0[m] * post[k] * c[idx0 + k]
 * where spec = conj(FFT_N(analytic reference)) / N on the bins kept, 0 elsewhere, and post
 * holds exp(-j 2 pi fc D k / fs) times the phase of the bin shift. Keeping N' bins around
 * the carrier is what decimates; the host picks N so that no gated lag wraps around.
 *
 * Each work-item transforms VEC recordings at once, one per vector lane (rows m0 + lane),
 * with radix-4 (and one radix-2) Stockham passes between two scratch arrays of N complex floatV: the
 * butterflies are plain vector arithmetic and every load and store is a whole vector,
 * which is what a CPU runtime vectorises well. Rows past n_meas are computed on zeros and
 * not stored. Batches of recordings start at m_begin. */

/* Stockham passes of a size-n transform, src -> dst, with ns the size of the sub-transforms
 * already done (Govindaraju et al., SC 2008, "FftIteration"). Element e of an array is
 * (re, im) = (a[2e], a[2e + 1]), each a floatV of VEC rows. tw[t] = exp(-j 2 pi t / N) for
 * the forward size N; sg = 1 forward, -1 inverse (conjugate twiddles). The twiddle of
 * sub-transform index k, output r is exp(-+j 2 pi k r / (ns R)) = tw[k r N / (ns R)]. */
#define CMUL(xr, xi, w, sg, yr, yi)                                                         \
    const floatV yr = (xr) * (w).x - (xi) * ((sg) * (w).y);                                \
    const floatV yi = (xr) * ((sg) * (w).y) + (xi) * (w).x;

#define STOCKHAM_R2(src, dst, n, ns, n_full, sg)                                            \
    for (int i = 0; i < ((n) >> 1); ++i) {                                                 \
        const int k = i & ((ns) - 1);                                                      \
        const float2 w = tw[k * ((n_full) / (2 * (ns)))];                                  \
        const floatV ar = src[2 * i], ai = src[2 * i + 1];                                 \
        const floatV br = src[2 * (i + ((n) >> 1))], bi = src[2 * (i + ((n) >> 1)) + 1];   \
        CMUL(br, bi, w, sg, tr, ti)                                                        \
        const int j = ((i - k) << 1) + k;                                                  \
        dst[2 * j] = ar + tr;                                                              \
        dst[2 * j + 1] = ai + ti;                                                          \
        dst[2 * (j + (ns))] = ar - tr;                                                     \
        dst[2 * (j + (ns)) + 1] = ai - ti;                                                 \
    }

#define STOCKHAM_R4(src, dst, n, ns, n_full, sg)                                            \
    for (int i = 0; i < ((n) >> 2); ++i) {                                                 \
        const int q = (n) >> 2;                                                            \
        const int k = i & ((ns) - 1);                                                      \
        const int ts = k * ((n_full) / (4 * (ns)));                                        \
        const float2 w1 = tw[ts], w2 = tw[2 * ts], w3 = tw[3 * ts];                        \
        const floatV v0r = src[2 * i], v0i = src[2 * i + 1];                               \
        CMUL(src[2 * (i + q)], src[2 * (i + q) + 1], w1, sg, v1r, v1i)                     \
        CMUL(src[2 * (i + 2 * q)], src[2 * (i + 2 * q) + 1], w2, sg, v2r, v2i)             \
        CMUL(src[2 * (i + 3 * q)], src[2 * (i + 3 * q) + 1], w3, sg, v3r, v3i)             \
        const floatV a0r = v0r + v2r, a0i = v0i + v2i, a1r = v0r - v2r, a1i = v0i - v2i;   \
        const floatV a2r = v1r + v3r, a2i = v1i + v3i;                                     \
        /* a3 = -+j (v1 - v3) */                                                           \
        const floatV a3r = (sg) * (v1i - v3i), a3i = -(sg) * (v1r - v3r);                  \
        const int j = ((i - k) << 2) + k;                                                  \
        dst[2 * j] = a0r + a2r;                                                            \
        dst[2 * j + 1] = a0i + a2i;                                                        \
        dst[2 * (j + (ns))] = a1r + a3r;                                                   \
        dst[2 * (j + (ns)) + 1] = a1i + a3i;                                               \
        dst[2 * (j + 2 * (ns))] = a0r - a2r;                                               \
        dst[2 * (j + 2 * (ns)) + 1] = a0i - a2i;                                           \
        dst[2 * (j + 3 * (ns))] = a1r - a3r;                                               \
        dst[2 * (j + 3 * (ns)) + 1] = a1i - a3i;                                           \
    }

/* a whole transform of size 2^log2 starting in buf[0]; a radix-2 pass first when log2 is
 * odd, then radix-4. Leaves `which` = index of the array holding the result. */
#define FFT_PASSES(buf0, buf1, log2, n_full, sg, which)                                     \
    {                                                                                      \
        const int nn = 1 << (log2);                                                        \
        int ns = 1;                                                                        \
        which = 0;                                                                         \
        if ((log2) & 1) {                                                                  \
            STOCKHAM_R2(buf0, buf1, nn, ns, n_full, sg)                                    \
            ns = 2;                                                                        \
            which = 1;                                                                     \
        }                                                                                  \
        for (; ns < nn; ns <<= 2) {                                                        \
            __global floatV *src = which ? buf1 : buf0;                                    \
            __global floatV *dst = which ? buf0 : buf1;                                    \
            STOCKHAM_R4(src, dst, nn, ns, n_full, sg)                                      \
            which = 1 - which;                                                             \
        }                                                                                  \
    }

__kernel void matched_fft(
    __global const float *signals,   /* (n_meas, n_samples) recordings                         */
    const int n_samples,             /* samples per recording                                  */
    const int n_meas,                /* recordings                                             */
    const int m_begin,               /* first recording of this batch                          */
    const int s_lo,                  /* first sample of the slice transformed                  */
    const int n_in,                  /* samples in the slice (<= N); the rest is zero padding  */
    const int log2_n,                /* forward size N = 2^log2_n                              */
    const int log2_nd,               /* inverse size N' = 2^log2_nd = N / D                    */
    __global const float2 *tw,       /* (N,) exp(-j 2 pi t / N)                                */
    const int bin0,                  /* forward bin of baseband bin 0 (nearest the carrier)    */
    __global const float2 *spec,     /* (N',) reference spectrum on baseband bins, FFT order   */
    const int idx0,                  /* inverse-transform index of profile sample 0            */
    const int n_lags,                /* profile samples wanted                                 */
    __global const float2 *post,     /* (n_lags,) phase per profile sample                     */
    __global const float2 *rot0,     /* (n_meas,) exp(-j 2 pi fc (t0_m + lag0 / fs))           */
    __global floatV *work,           /* (n_items, 4 N) floatV scratch: two arrays of N complex */
    const int out_stride,            /* row length of out                                      */
    __global float2 *out)            /* (n_meas, out_stride) baseband profiles                 */
{
    const int g = get_global_id(0);
    const int m0 = m_begin + g * VEC;
    const int n = 1 << log2_n, nd = 1 << log2_nd;
    __global floatV *a = work + (size_t)g * 4 * n;
    __global floatV *b = a + 2 * n;

    /* load VEC rows, lane l = row m0 + l, zero past the slice and past the last row; lanes
     * are written as scalars through a float pointer (no private union) */
    for (int e = 0; e < n; ++e) {
        __global float *lane = (__global float *)(a + 2 * e);
        for (int l = 0; l < VEC; ++l) {
            const int m = m0 + l;
            lane[l] = (e < n_in && m < n_meas) ? signals[(size_t)m * n_samples + s_lo + e] : 0.0f;
        }
        a[2 * e + 1] = (floatV)(0.0f);
    }
    /* forward transform */
    int which;
    FFT_PASSES(a, b, log2_n, n, 1.0f, which)
    __global floatV *x_f = which ? b : a;    /* the spectrum */
    __global floatV *y = which ? a : b;      /* the other array */

    /* keep N' bins around the carrier, times the reference spectrum */
    for (int j = 0; j < nd; ++j) {
        const int jj = (j < (nd >> 1)) ? j : j - nd;
        const int bin = (bin0 + jj) & (n - 1);
        const float2 s = spec[j];
        const floatV xr = x_f[2 * bin], xi = x_f[2 * bin + 1];
        y[2 * j] = xr * s.x - xi * s.y;
        y[2 * j + 1] = xr * s.y + xi * s.x;
    }
    /* inverse transform of size N' (conjugate twiddles; the same table) */
    FFT_PASSES(y, x_f, log2_nd, n, -1.0f, which)
    __global floatV *c = which ? x_f : y;

    for (int k = 0; k < n_lags; ++k) {
        const int e = (idx0 + k) & (nd - 1);
        __global const float *cr = (__global const float *)(c + 2 * e);
        __global const float *ci = (__global const float *)(c + 2 * e + 1);
        const float2 pk = post[k];
        for (int l = 0; l < VEC; ++l) {
            const int m = m0 + l;
            if (m < n_meas) {
                const float2 r0 = rot0[m];
                /* complex products as whole-vector operations with swizzles: a (float2)(x, y)
                 * built from scalar products trips Oclgrind 19.10's uninitialised-value check */
                const float2 conj_sign = (float2)(-1.0f, 1.0f);
                const float2 w = r0.xx * pk + r0.yy * pk.yx * conj_sign;
                const float2 z = (float2)(cr[l], ci[l]);
                out[(size_t)m * out_stride + k] = z.xx * w + z.yy * w.yx * conj_sign;
            }
        }
    }
}
