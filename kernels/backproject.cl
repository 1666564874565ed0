/* 3-D bistatic backprojection of complex baseband range profiles.
 *
 * For every voxel v and measurement m:
 *   path  = |v - tx_m| + |v - rx_m|                      (m)
 *   idx   = path * fs / c - s0_m                          (profile samples)
 *   value = lerp(profile_m, idx) * exp(+j 2 pi fc path / c)
 * and the image is the sum over m. Samples outside [0, n_lags - 1] contribute nothing.
 * The carrier phase is reduced to cycles in [-0.5, 0.5] before sin/cos, so float32 keeps
 * it to ~1e-5 cycles at a few metres.
 *
 * Needs common.cl. Each work-item owns VEC consecutive voxels of the flattened grid
 * (C order, z fastest), so a single plane costs a plane; voxels past n_vox are padding.
 * Measurements are processed in chunks [m_begin, m_end); the host accumulates chunks. */

__kernel void backproject(
    __global const float2 *profiles, /* (n_meas, n_lags) baseband complex range profiles      */
    const int n_lags,                /* samples per profile                                   */
    __global const float4 *tx,       /* (n_meas,) speaker position xyz, m (w unused)          */
    __global const float4 *rx,       /* (n_meas,) microphone position xyz, m (w unused)       */
    __global const float *s0,        /* (n_meas,) profile index of zero delay: t_start * fs   */
    const float samples_per_m,       /* fs / c, samples per metre of path                     */
    const float cycles_per_m,        /* fc / c, carrier cycles per metre of path              */
    const float4 origin,             /* centre of voxel (0, 0, 0), m                          */
    const float4 step,               /* voxel spacing along x, y, z, m                        */
    const int ny,                    /* voxels along y                                        */
    const int nz,                    /* voxels along z                                        */
    const int m_begin,               /* first measurement of this chunk                       */
    const int m_end,                 /* one past the last measurement of this chunk           */
    const int accumulate,            /* 0: overwrite the image, 1: add to it                  */
    __global float *image_re,        /* (n_vox_padded,) real part of the image                */
    __global float *image_im)        /* (n_vox_padded,) imaginary part of the image           */
{
    const int v0 = get_global_id(0) * VEC;
    int vi[VEC];
    for (int l = 0; l < VEC; ++l) vi[l] = v0 + l;
    const intV vox = vloadV(0, vi);
    const intV iz = vox % nz;
    const intV iy = (vox / nz) % ny;
    const intV ix = vox / (nz * ny);
    const floatV X = origin.x + step.x * CAT(convert_float, VEC)(ix);
    const floatV Y = origin.y + step.y * CAT(convert_float, VEC)(iy);
    const floatV Z = origin.z + step.z * CAT(convert_float, VEC)(iz);
    const float last = (float)(n_lags - 1);

    floatV acc_re = (floatV)(0.0f);
    floatV acc_im = (floatV)(0.0f);
    int ii[VEC];
    float a_re[VEC], a_im[VEC], b_re[VEC], b_im[VEC];

    for (int m = m_begin; m < m_end; ++m) {
        const float4 t = tx[m];
        const float4 r = rx[m];
        const floatV dtx = X - t.x, dty = Y - t.y, dtz = Z - t.z;
        const floatV drx = X - r.x, dry = Y - r.y, drz = Z - r.z;
        const floatV path = sqrt(mad(dtx, dtx, mad(dty, dty, dtz * dtz)))
                          + sqrt(mad(drx, drx, mad(dry, dry, drz * drz)));
        const floatV idx = mad(path, (floatV)(samples_per_m), (floatV)(-s0[m]));
        const intV inside = (idx >= 0.0f) & (idx <= last);
        const intV i0 = clamp(convert_intV(floor(clamp(idx, -1.0f, last + 1.0f))), 0, n_lags - 2); /* n_lags >= 2 */
        const floatV w = idx - CAT(convert_float, VEC)(i0);
        vstoreV(i0, 0, ii);
        __global const float2 *row = profiles + (size_t)m * n_lags;
        for (int l = 0; l < VEC; ++l) {
            const float4 ab = vload4(0, (__global const float *)(row + ii[l]));
            a_re[l] = ab.x; a_im[l] = ab.y; b_re[l] = ab.z; b_im[l] = ab.w;
        }
        const floatV are = vloadV(0, a_re), aim = vloadV(0, a_im);
        const floatV re = select((floatV)(0.0f), mad(w, vloadV(0, b_re) - are, are), inside);
        const floatV im = select((floatV)(0.0f), mad(w, vloadV(0, b_im) - aim, aim), inside);
        floatV cyc = path * cycles_per_m;
        cyc -= rint(cyc);
        floatV c;
        const floatV s = sincos(6.28318530718f * cyc, &c);
        acc_re += re * c - im * s;
        acc_im += re * s + im * c;
    }
    if (accumulate) {
        acc_re += vloadV(0, image_re + v0);
        acc_im += vloadV(0, image_im + v0);
    }
    vstoreV(acc_re, 0, image_re + v0);
    vstoreV(acc_im, 0, image_im + v0);
}
