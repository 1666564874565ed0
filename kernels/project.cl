/* Forward projection: complex voxels -> complex baseband range profiles, the exact adjoint of
 * backproject.cl.
 *
 * backproject.cl forms image[v] = sum_m sum_k B[v, (m, k)] p[m, k] with, for voxel v and
 * measurement m,
 *   path = |v - tx_m| + |v - rx_m|,  idx = path / (c_m dtau) - s0_m,
 *   i0 = clamp(floor(idx), 0, n_lags - 2),  w = idx - i0,
 *   B[v, (m, i0)] = (1 - w) e^{+j 2 pi fc path / c_m},  B[v, (m, i0 + 1)] = w e^{...}
 * (zero where idx is outside [0, n_lags - 1]). This kernel computes its adjoint,
 *   p[m, k] = sum_v conj(B[v, (m, k)]) x[v],
 * with the carrier split as backproject.cl splits it: e^{j 2 pi fc path / c_m} =
 * R_{m,i0} e^{j phi (w - 1/2)}. Each voxel spreads (1 - w) and w of x[v] e^{-j phi (w - 1/2)}
 * onto the two slots (A, B) of record i0; the host multiplies record k by conj(R_mk) and adds
 * slot A to lag k and slot B to lag k + 1 (clsas/inverse/project_opencl.py), so the two
 * kernels round alike and stay adjoint to float32 accuracy.
 *
 * Strategy (no atomics): the scatter is made race-free by ownership. Work-item (i, j) owns
 * measurement m = m_begin + j and the contiguous voxel slab [i * slab, (i + 1) * slab) (in
 * blocks of VEC voxels, C order, z fastest); it accumulates into its own private copy of the
 * profile, out[(j * n_items + i) * n_lags + k], which no other work-item reads or writes. A
 * second kernel, project_sum, adds the n_items copies of each measurement's profile. Within a
 * work-item the VEC lanes' geometry (path, lag, weight, carrier) is computed as vectors and the
 * scatter runs lane by lane (lanes may hit the same lag). Deterministic: same order every run.
 *
 * Transducer beams: built with beam.cl and -DBEAM, the real two-way weight of each
 * voxel-measurement pair scales the carrier (c, s) exactly as in backproject.cl, so it enters
 * (vr, vi) as the same real factor and the two kernels stay exact adjoints. Without -DBEAM the
 * hooks expand to nothing (the omnidirectional kernel, bit for bit).
 *
 * Needs common.cl (and beam.cl for -DBEAM). Voxels past n_vox are padding with x = 0. */

#ifndef BEAM_WEIGHT /* built without beam.cl: omnidirectional */
#define BEAM_ARGS
#define BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m)
#endif

__kernel void project(
    __global const float *x_re,      /* (n_vox_padded,) real part of the voxels, 0 on padding  */
    __global const float *x_im,      /* (n_vox_padded,) imaginary part                         */
    const int n_lags,                /* samples per profile (>= 2)                              */
    __global const float4 *tx,       /* (n_meas,) speaker position xyz, m; w: 1 / (c_m dtau),
                                        profile samples per metre of path                      */
    __global const float4 *rx,       /* (n_meas,) microphone position xyz, m; w unused          */
    __global const float *s0,        /* (n_meas,) profile index of zero delay: tau0_m / dtau   */
    const float4 origin,             /* centre of voxel (0, 0, 0), m                           */
    const float4 step,               /* voxel spacing along x, y, z, m                         */
    const int ny,                    /* voxels along y                                         */
    const int nz,                    /* voxels along z                                         */
    const float phi,                 /* 2 pi fc dtau, carrier radians per sample, <= 0.6 pi     */
    const int n_blocks,              /* blocks of VEC voxels (the padded grid / VEC)           */
    const int m_begin,               /* measurement of work-items (., 0)                       */
    __global float4 *out             /* (n_chunk_meas, n_items, n_lags) partial records,
                                        (A re, A im, B re, B im); fully overwritten            */
    BEAM_ARGS)                       /* beam.cl: the beam's buffers with -DBEAM, else nothing  */
{
    const int item = get_global_id(0);
    const int n_items = get_global_size(0);
    const int j = get_global_id(1);
    const int m = m_begin + j;
    const float4 t = tx[m];
    const float4 r = rx[m];
    const float sm = s0[m];
    const float last = (float)(n_lags - 1);
    __global float4 *acc = out + ((size_t)j * n_items + item) * n_lags;
    for (int k = 0; k < n_lags; ++k) acc[k] = (float4)(0.0f);

    const int per = (n_blocks + n_items - 1) / n_items;
    const int b_begin = item * per;
    const int b_end = min(n_blocks, b_begin + per);
    for (int b = b_begin; b < b_end; ++b) {
        const int v0 = b * VEC;
        lanes_f fx, fy, fz;
        for (int l = 0; l < VEC; ++l) {
            const int vox = v0 + l;
            const int yz = vox / nz, iz = vox - yz * nz;   /* no %: see backproject.cl */
            const int ix = yz / ny, iy = yz - ix * ny;
            fx.s[l] = origin.x + step.x * (float)ix;
            fy.s[l] = origin.y + step.y * (float)iy;
            fz.s[l] = origin.z + step.z * (float)iz;
        }
        const floatV X = fx.v, Y = fy.v, Z = fz.v;
        const floatV dtx = X - t.x, dty = Y - t.y, dtz = Z - t.z;
        const floatV drx = X - r.x, dry = Y - r.y, drz = Z - r.z;
        const floatV path = vsqrt(dtx * dtx + dty * dty + dtz * dtz)
                          + vsqrt(drx * drx + dry * dry + drz * drz);
        const floatV idx = path * t.w - sm;
        const intV inside = (idx >= 0.0f) & (idx <= last);
        const floatV i0 = lag_floor(idx, last);
        const floatV w = inside ? idx - i0 : (floatV)(0.5f);   /* in [0, 1] where it counts */
        floatV c;
        floatV s = sincos_small(phi * (w - 0.5f), &c);
        BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m);
        const floatV xr = vloadV(0, x_re + v0), xi = vloadV(0, x_im + v0);
        /* x e^{-j phi (w - 1/2)} = (xr c + xi s) + j (xi c - xr s); zero outside the window */
        lanes_f vr, vi, lw, li;
        vr.v = inside ? xr * c + xi * s : (floatV)(0.0f);
        vi.v = inside ? xi * c - xr * s : (floatV)(0.0f);
        lw.v = w;
        li.v = i0;
        for (int l = 0; l < VEC; ++l) {
            const float2 val = (float2)(vr.s[l], vi.s[l]);
            acc[(int)li.s[l]] += (float4)((1.0f - lw.s[l]) * val, lw.s[l] * val);
        }
    }
}

/* Sum the n_items partial records of each measurement of a chunk into the records. */
__kernel void project_sum(
    __global const float4 *part,     /* (n_chunk_meas, n_items, n_lags) partial records         */
    const int n_items,               /* partial copies per measurement                          */
    const int n_lags,                /* records per profile                                     */
    const int m_begin,               /* first measurement of the chunk                          */
    __global float4 *records)        /* (n_meas, n_lags) records (A re, A im, B re, B im)       */
{
    const int k = get_global_id(0);
    const int j = get_global_id(1);
    if (k >= n_lags) return;
    __global const float4 *p = part + (size_t)j * n_items * n_lags + k;
    float4 sum = (float4)(0.0f);
    for (int i = 0; i < n_items; ++i) sum += p[(size_t)i * n_lags];
    records[(size_t)(m_begin + j) * n_lags + k] = sum;
}
