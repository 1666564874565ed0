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
    const int n_lags,                /* lags wanted per measurement                         */
    __global const float2 *rot,      /* (out_stride,) exp(-j 2 pi fc k / fs), k = 0..       */
    __global const float2 *rot0,     /* (n_meas,) exp(-j 2 pi fc (t0_m + lag0 / fs))        */
    const int out_stride,            /* row length of out (multiple of VEC)                 */
    __global float2 *out)            /* (n_meas, out_stride) baseband profiles              */
{
    const int blk = get_global_id(0);
    const int m = get_global_id(1);
    const int k0 = blk * VEC;               /* first profile sample of this work-item */
    if (k0 >= out_stride) return;
    const int L = lag0 + k0;                /* first lag, samples */
    __global const float *row = signals + (size_t)m * n_samples;

    floatV acc_re = (floatV)(0.0f);
    floatV acc_im = (floatV)(0.0f);
    if (L >= 0 && L + VEC - 1 + n_ref - 1 < n_samples) {
        /* fast path: the whole window lies inside the recording */
        __global const float *x = row + L;
        for (int n = 0; n < n_ref; ++n) {
            lanes_f xv;
            for (int l = 0; l < VEC; ++l) xv.s[l] = x[n + l];
            const float2 r = ref[n];
            acc_re += xv.v * r.x;
            acc_im += xv.v * r.y;
        }
    } else {
        /* edge path: samples outside the recording contribute nothing */
        float re[VEC], im[VEC];
        for (int l = 0; l < VEC; ++l) {
            float sr = 0.0f, si = 0.0f;
            const int lag = L + l;
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

    /* rotate to baseband: exp(-j 2 pi fc (t0 + (lag0 + k)/fs)) = rot0[m] * rot[k] */
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
