/* 3-D bistatic backprojection of complex baseband range profiles.
 *
 * For every voxel v and measurement m (the definition, clsas/formation/bp_numpy.py):
 *   path  = |v - tx_m| + |v - rx_m|                      (m)
 *   idx   = path / (c_m dtau) - s0_m                      (profile samples)
 *   value = lerp(profile_m, idx) * exp(+j 2 pi fc path / c_m)
 * and the image is the sum over m. The speed of sound c_m is per measurement (air that
 * changes during a scan): its path scale rides in the w lane of tx. Samples outside
 * [0, n_lags - 1] contribute nothing.
 *
 * The carrier is split at the profile's samples. Since fc path / c_m = fc dtau (idx + s0_m),
 * with idx = k + f (k = floor(idx), f in [0, 1]) and phi = 2 pi fc dtau,
 *   value = [(1 - f) q_k + f r_k] * exp(j phi (f - 1/2)),
 *   q_k = p_k R_mk,  r_k = p_{k+1} R_mk,  R_mk = exp(j phi (k + 1/2 + s0_m)),
 * exactly. The host writes the records (q_k, r_k) already rotated (in double precision), so the
 * kernel evaluates only the sub-sample rotation, a short polynomial for |phi (f - 1/2)| <= 0.6 pi
 * (the host upsamples the profile, which linear interpolation leaves unchanged, until
 * fc dtau <= 0.6). No per-pair range reduction and no full carrier phase in float32.
 *
 * Needs common.cl. Each work-item owns VEC consecutive voxels of the flattened grid
 * (C order, z fastest), so a single plane costs a plane; voxels past n_vox are padding.
 * Measurements are processed in chunks [m_begin, m_end); the host accumulates chunks. The
 * image is two float planes, or with -DCOMPLEX_IMAGE one interleaved complex array.
 *
 * -DLOCAL_PROFILES: per measurement, the work-group copies the run of seg_len records its voxels
 * read (from the smallest left sample of its lanes inside the window and the grid, found with a
 * local atomic_min) into local memory, and its lanes read them there: the same values, so the
 * same image. The host sizes seg_len from the work-group's bounding box (its path spread in
 * samples, plus 2); it needs a local size. Two barriers per measurement; the atomic's slot alternates with m's parity, so the
 * slot of m + 1 is reset while m's is still read.
 *
 * -DHALF_PROFILES: the records are stored as half (4 per record, read with vload_half4, core
 * OpenCL), scaled by the host into half's range (it scales the image back): half the bytes per
 * pair gathered, float arithmetic. Not with -DLOCAL_PROFILES.
 *
 * -DRANGE_EXPANSION=R (VEC / R = 1, 2 or 4): a work-item whose VEC voxels lie in one z row splits them
 * into runs of R and evaluates the two distances exactly only at each run's middle point
 * (between its first and last voxel); voxel s steps from it (s = place - (R - 1) / 2) takes
 * the second-order Taylor expansion in s, d0 + s g + s^2 h with a = ref - p, d0 = |a|,
 * g = a_z dz / d0, h = (dz^2 - g^2) / (2 d0), folded into the lag: idx = A + s (B + s C), two
 * multiply-adds per voxel. Work-items across a row's end are exact (with -DROWS_ALIGNED, for nz a
 * multiple of VEC, there are none and the exact branch is left out). The path error (the
 * remainder, third order in s dz / d0) is bounded per geometry by the host
 * (clsas/formation/bp_numpy.py: range_expansion_error), which runs the plain kernel where the
 * bound exceeds what the caller allows. */

#ifdef COMPLEX_IMAGE /* the image as one interleaved complex array (re, im), read back as complex64 */
#define IMAGE_ARGS __global float *image /* (n_vox_padded, 2) complex image, (re, im) per voxel */
#else /* the image as two planes */
#define IMAGE_ARGS __global float *image_re, /* (n_vox_padded,) real part of the image */ \
                   __global float *image_im  /* (n_vox_padded,) imaginary part of the image */
#endif

#ifdef HALF_PROFILES /* the records as half, gathered with vload_half4 */
#ifdef LOCAL_PROFILES
#error "HALF_PROFILES and LOCAL_PROFILES do not combine"
#endif
#define PAIRS_T half
#define RECORD_ELEMS 4
#undef G4
#define G4(src, li, l) vload_half4((int)(li).s[l], (src))
/* lerp_pairs (common.cl) of a row of half records */
inline void lerp_pairs_half(__global const half *row, const floatV idx, const float last, floatV *re, floatV *im,
                            floatV *w_out)
{
    const intV inside = (idx >= 0.0f) & (idx <= last);
    lanes_f li;
    li.v = lag_floor(idx, last);
    const floatV w = idx - li.v;
    GATHER_PAIRS(row, li, are, aim, bre, bim)
    *re = inside ? are + w * (bre - are) : (floatV)(0.0f);
    *im = inside ? aim + w * (bim - aim) : (floatV)(0.0f);
    *w_out = inside ? w : (floatV)(0.5f);
}
#undef G4
#define G4(src, li, l) (src)[(int)(li).s[l]]
#define LERP_ROW lerp_pairs_half
#else
#define PAIRS_T float4
#define RECORD_ELEMS 1
#define LERP_ROW lerp_pairs
#endif

#ifdef LOCAL_PROFILES /* the records of a work-group's measurement staged in local memory */
#define LOCAL_ARGS __local float4 *seg, /* (seg_len,) the records the work-group reads, from k_lo */ \
                   const int seg_len,    /* records per staged run, >= the group's spread + 2       */ \
                   const int n_vox,      /* voxels of the grid (lanes past it: padding, not staged)  */
#else
#define LOCAL_ARGS
#endif

#ifdef RANGE_EXPANSION /* the distances by their expansion along z around each run's middle */
#define RUN RANGE_EXPANSION
#if VEC % RUN
#error "RANGE_EXPANSION must divide VEC"
#endif
#define N_RUNS (VEC / RUN)

/* runT: one lane per run of the work-item (float where there is one); RUN_SQRT: its lanes' square
 * roots, as vsqrt takes them (common.cl: lane by lane with the compiler's own, else the builtin);
 * RUN_FIRST: the runs' first lanes of a lanes_f; SPREAD: each run's value over its lanes, selected
 * by R (intV, each lane's run) with vector ?: rather than a swizzle such as .s00001111 */
#if N_RUNS == 1
#define runT float
#if defined(__clang__) && !defined(CLSAS_OPENCL_SQRT)
#define RUN_SQRT(q) __builtin_sqrtf(q)
#else
#define RUN_SQRT(q) sqrt(q)
#endif
#define RUN_FIRST(f) ((f).s[0])
#define SPREAD(x) (x)
#elif N_RUNS == 2
#define runT float2
#if defined(__clang__) && !defined(CLSAS_OPENCL_SQRT)
#define RUN_SQRT(q) ((float2)(__builtin_sqrtf((q).s0), __builtin_sqrtf((q).s1)))
#else
#define RUN_SQRT(q) sqrt(q)
#endif
#define RUN_FIRST(f) ((float2)((f).s[0], (f).s[RUN]))
#define SPREAD(x) ((R == 0) ? (floatV)((x).s0) : (floatV)((x).s1))
#elif N_RUNS == 4 && VEC == 16
#define runT float4
#if defined(__clang__) && !defined(CLSAS_OPENCL_SQRT)
#define RUN_SQRT(q) ((float4)(__builtin_sqrtf((q).s0), __builtin_sqrtf((q).s1), __builtin_sqrtf((q).s2), \
                              __builtin_sqrtf((q).s3)))
#else
#define RUN_SQRT(q) sqrt(q)
#endif
#define RUN_FIRST(f) ((float4)((f).s[0], (f).s[RUN], (f).s[2 * RUN], (f).s[3 * RUN]))
#define SPREAD(x) ((R < 2) ? ((R == 0) ? (floatV)((x).s0) : (floatV)((x).s1)) \
                           : ((R == 2) ? (floatV)((x).s2) : (floatV)((x).s3)))
#else
#error "RANGE_EXPANSION: runs of 4 voxels or more (1, 2 or 4 runs per work-item)"
#endif

/* The lags idx = (|v - t| + |v - r|) t.w - s0 (t.w: profile samples per metre of path) of the
 * lanes of a work-item in one z row: idx = a + s (b + s c) per run, from the run's middle
 * (ref_x, ref_y, ref_z) (t_xy, r_xy its squared distances to tx and rx across z), two square
 * roots and one division per run; S holds each lane's s (voxel steps dz from its run's middle), R
 * its run. */
inline floatV expanded_lags(const float ref_x, const float ref_y, const runT ref_z, const float dz, const float4 t,
                            const float4 r, const float s0, const floatV S, const intV R)
{
    const float tx = ref_x - t.x, ty = ref_y - t.y, rx = ref_x - r.x, ry = ref_y - r.y;
    const float t_xy = tx * tx + ty * ty, r_xy = rx * rx + ry * ry;
    const runT tz = ref_z - t.z, rz = ref_z - r.z;
    const runT dt = RUN_SQRT(t_xy + tz * tz), dr = RUN_SQRT(r_xy + rz * rz);
    const runT inv = 1.0f / (dt * dr); /* 1 / dt = dr inv, 1 / dr = dt inv */
    const runT it = dr * inv, ir = dt * inv;
    const runT gt = tz * dz * it, gr = rz * dz * ir;
    const runT a = (dt + dr) * t.w - s0;
    const runT b = (gt + gr) * t.w;
    const runT c = 0.5f * ((dz * dz - gt * gt) * it + (dz * dz - gr * gr) * ir) * t.w;
    return SPREAD(a) + S * (SPREAD(b) + S * SPREAD(c));
}
#endif

#ifndef BEAM_WEIGHT /* built without beam.cl: omnidirectional */
#define BEAM_ARGS
#define BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m)
#endif

#ifdef LOCAL_PROFILES
/* lerp_pairs (common.cl) reading the records from a run staged in local memory: the group's
 * smallest left sample goes to k_lo[parity] (atomic_min), the run [k_lo, k_lo + seg_len) of
 * `row` is copied to `seg` by the group's work-items, and each lane interpolates there. Every
 * work-item of the group calls it once per measurement (it holds barriers); k_lo[1 - parity] is
 * reset for the next measurement (nobody reads it until then). */
inline void stage_and_lerp(__global const float4 *row, const int n_lags, const floatV idx, const float last,
                           const intV real, __local float4 *seg, const int seg_len, __local int *k_lo,
                           const int parity, floatV *re, floatV *im, floatV *w_out)
{
    const intV inside = (idx >= 0.0f) & (idx <= last);
    lanes_f li;
    li.v = lag_floor(idx, last);
    lanes_i counted;
    counted.v = inside & real;
    float lo = last;
    for (int l = 0; l < VEC; ++l) lo = (counted.s[l] && li.s[l] < lo) ? li.s[l] : lo;
    atomic_min(&k_lo[parity], (int)lo);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int k0 = min(k_lo[parity], n_lags - 2); /* n_lags - 2 where no lane of the group counts */
    const int n_seg = min(seg_len, n_lags - k0);  /* records of the run inside the row, >= 2 */
    const int lid = (int)get_local_id(0), nl = (int)get_local_size(0);
    if (lid == 0) k_lo[1 - parity] = n_lags;
    for (int k = lid; k < n_seg; k += nl) seg[k] = row[k0 + k];
    barrier(CLK_LOCAL_MEM_FENCE);
    const floatV w = idx - li.v;
    lanes_f rel;
    rel.v = li.v - (float)k0; /* in [0, seg_len - 1] where the lane is inside */
    rel.v = (rel.v > (float)(n_seg - 1)) ? (floatV)((float)(n_seg - 1)) : rel.v; /* lanes not counted: */
    rel.v = (rel.v < 0.0f) ? (floatV)(0.0f) : rel.v;                                /* read, unused       */
    GATHER_PAIRS(seg, rel, are, aim, bre, bim)
    *re = inside ? are + w * (bre - are) : (floatV)(0.0f);
    *im = inside ? aim + w * (bim - aim) : (floatV)(0.0f);
    *w_out = inside ? w : (floatV)(0.5f);
}
#endif

__kernel void backproject(
    __global const PAIRS_T *pairs,   /* (n_meas, n_lags) records (q_k, r_k) above: the samples
                                        k and k + 1 of the baseband profile rotated by R_mk,
                                        as (re, im, re, im); p[n_lags] = 0; float4, or 4 half
                                        with -DHALF_PROFILES                                  */
    const int n_lags,                /* samples per profile                                   */
    __global const float4 *tx,       /* (n_meas,) speaker position xyz, m; w: 1 / (c_m dtau),
                                        profile samples per metre of path                     */
    __global const float4 *rx,       /* (n_meas,) microphone position xyz, m; w unused         */
    __global const float *s0,        /* (n_meas,) profile index of zero delay: tau0_m / dtau  */
    const float4 origin,             /* centre of voxel (0, 0, 0), m                          */
    const float4 step,               /* voxel spacing along x, y, z, m                        */
    const int ny,                    /* voxels along y                                        */
    const int nz,                    /* voxels along z                                        */
    const float phi,                 /* 2 pi fc dtau, carrier radians per profile sample, <= 0.6 pi */
    const int m_begin,               /* first measurement of this chunk                       */
    const int m_end,                 /* one past the last measurement of this chunk           */
    const int accumulate,            /* 0: overwrite the image, 1: add to it                  */
    LOCAL_ARGS                       /* -DLOCAL_PROFILES: the staged run of records           */
    IMAGE_ARGS                       /* the image: two planes, or complex with -DCOMPLEX_IMAGE */
    BEAM_ARGS)                       /* beam.cl: the beam's buffers with -DBEAM, else nothing */
{
    const int v0 = get_global_id(0) * VEC;
    lanes_i vox;
    for (int l = 0; l < VEC; ++l) vox.s[l] = v0 + l;
    lanes_f fx, fy, fz;
    for (int l = 0; l < VEC; ++l) {
        /* x - (x / n) * n rather than %: a div/rem pair becomes LLVM's `freeze`, which
         * Oclgrind's uninitialised-value checker cannot follow */
        const int yz = vox.s[l] / nz, iz = vox.s[l] - yz * nz;
        const int ix = yz / ny, iy = yz - ix * ny;
        fx.s[l] = origin.x + step.x * (float)ix;
        fy.s[l] = origin.y + step.y * (float)iy;
        fz.s[l] = origin.z + step.z * (float)iz;
    }
    const floatV X = fx.v, Y = fy.v, Z = fz.v;
    const float last = (float)(n_lags - 1);
#ifdef RANGE_EXPANSION
#ifdef ROWS_ALIGNED /* nz is a multiple of VEC: every work-item's voxels lie in one z row */
    const int along_z = 1;
#else
    const int along_z = (v0 - (v0 / nz) * nz) + VEC <= nz; /* the work-item's voxels in one z row */
#endif
    lanes_f s_lane;
    lanes_i run_of;
    for (int l = 0; l < VEC; ++l) {
        run_of.s[l] = l / RUN;
        s_lane.s[l] = (float)(l - run_of.s[l] * RUN) - 0.5f * (float)(RUN - 1);
    }
    const floatV S = s_lane.v;
    const intV R = run_of.v;
    const runT ref_z = RUN_FIRST(fz) + 0.5f * (float)(RUN - 1) * step.z; /* each run's middle */
#endif

    floatV acc_re = (floatV)(0.0f);
    floatV acc_im = (floatV)(0.0f);
#ifdef LOCAL_PROFILES
    const intV real = vox.v < n_vox; /* lanes of the grid, not padding */
    __local int k_lo[2]; /* the group's smallest left sample, one slot per parity of m */
    if (get_local_id(0) == 0) {
        k_lo[0] = n_lags;
        k_lo[1] = n_lags;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
#endif

    for (int m = m_begin; m < m_end; ++m) {
        const float4 t = tx[m];
        const float4 r = rx[m];
        const floatV dtx = X - t.x, dty = Y - t.y, dtz = Z - t.z;
        const floatV drx = X - r.x, dry = Y - r.y, drz = Z - r.z;
#ifdef RANGE_EXPANSION
        const floatV idx = along_z ? expanded_lags(fx.s[0], fy.s[0], ref_z, step.z, t, r, s0[m], S, R)
                                   : (vsqrt(dtx * dtx + dty * dty + dtz * dtz)
                                      + vsqrt(drx * drx + dry * dry + drz * drz)) * t.w - s0[m];
#else
        const floatV path = vsqrt(dtx * dtx + dty * dty + dtz * dtz)
                          + vsqrt(drx * drx + dry * dry + drz * drz);
        const floatV idx = path * t.w - s0[m];
#endif
        floatV re, im, f;
#ifdef LOCAL_PROFILES
        stage_and_lerp(pairs + (size_t)m * n_lags, n_lags, idx, last, real, seg, seg_len, k_lo, m & 1, &re, &im,
                       &f);
#else
        LERP_ROW(pairs + (size_t)m * n_lags * RECORD_ELEMS, idx, last, &re, &im, &f);
#endif
        floatV c;
        floatV s = sincos_small(phi * (f - 0.5f), &c);
        BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m);
        acc_re += re * c - im * s;
        acc_im += re * s + im * c;
    }
#ifdef COMPLEX_IMAGE
    lanes_f out_re, out_im;
    out_re.v = acc_re;
    out_im.v = acc_im;
    __global float *out = image + 2 * (size_t)v0;
    if (accumulate) {
        for (int l = 0; l < VEC; ++l) {
            out[2 * l] += out_re.s[l];
            out[2 * l + 1] += out_im.s[l];
        }
    } else {
        for (int l = 0; l < VEC; ++l) {
            out[2 * l] = out_re.s[l];
            out[2 * l + 1] = out_im.s[l];
        }
    }
#else
    if (accumulate) {
        acc_re += vloadV(0, image_re + v0);
        acc_im += vloadV(0, image_im + v0);
    }
    vstoreV(acc_re, 0, image_re + v0);
    vstoreV(acc_im, 0, image_im + v0);
#endif
}
