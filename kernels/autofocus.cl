/* Gradient of an image-focus metric through 3-D bistatic backprojection.
 *
 * The image is I(v) = sum_m s_m(tau_m(v)), with s_m the analytic (carrier-bearing) range
 * profile of measurement m and tau_m(v) = (|v - tx_m| + |v - rx_m|) / c_m, evaluated as
 * backproject.cl does (linear interpolation of the baseband profile, carrier restored). For a
 * metric whose change is dM = sum_v Re(conj(G(v)) dI(v)) (G: the metric's weight per voxel),
 * this kernel returns, for each measurement m, the five sums over voxels
 *
 *   r(v)  = Re(conj(G(v)) s'_m(tau_m(v)))             s' = d s / d tau (per second)
 *   out   = ( sum r,  sum r * -(u_tx + u_rx).x,  .y,  .z,  sum r * path )
 *
 * where u_tx = (v - tx_m) / |v - tx_m| (likewise u_rx) and path = |v - tx_m| + |v - rx_m|.
 * With these, dM / d(delay of m) = -out0, dM / d(carriage shift of m) = out1..3 / c_m and
 * dM / d c_m = -out4 / c_m^2 (see clsas/focus/gradient_numpy.py, the specification). The
 * derivative of the linear interpolation is its slope (b - a) / dtau: the exact derivative of
 * the image the kernel forms, away from sample knots. Samples outside [0, n_lags - 1] add 0.
 *
 * Needs common.cl. Work-item (i, j) owns measurement m_begin + j and the voxel blocks
 * i, i + n_items, i + 2 n_items, ... (VEC voxels each, C order, z fastest); it writes its five
 * partial sums to out[((m) * n_items + i) * 5 + k] and the host adds the n_items partials.
 * No work-item reads what another writes. Voxels past n_vox are padding with G = 0. */

__kernel void focus_gradient(
    __global const float4 *pairs,    /* (n_meas, n_lags) (p[k], p[k+1]) of the baseband complex
                                        profiles, as (re, im, re, im); p[n_lags] = 0           */
    const int n_lags,                /* samples per profile                                   */
    __global const float4 *tx,       /* (n_meas,) speaker position xyz, m; w: 1 / (c_m dtau)  */
    __global const float4 *rx,       /* (n_meas,) microphone position xyz, m; w: fc / c_m     */
    __global const float *s0,        /* (n_meas,) profile index of zero delay: tau0_m / dtau  */
    const float4 origin,             /* centre of voxel (0, 0, 0), m                          */
    const float4 step,               /* voxel spacing along x, y, z, m                        */
    const int ny,                    /* voxels along y                                        */
    const int nz,                    /* voxels along z                                        */
    const int n_blocks,              /* blocks of VEC voxels (the padded grid / VEC)          */
    const float2 deriv,              /* x: 1 / dtau (1/s); y: 2 pi fc (rad/s)                 */
    __global const float *weight_re, /* (n_vox_padded,) Re G, 0 on padding                    */
    __global const float *weight_im, /* (n_vox_padded,) Im G, 0 on padding                    */
    const int m_begin,               /* measurement of work-items (., 0)                      */
    __global float *out)             /* (n_meas, n_items, 5) partial sums                     */
{
    const int item = get_global_id(0);
    const int n_items = get_global_size(0);
    const int m = m_begin + get_global_id(1);
    const float4 t = tx[m];
    const float4 r = rx[m];
    const float sm = s0[m];
    const float last = (float)(n_lags - 1);
    __global const float4 *row = pairs + (size_t)m * n_lags;

    floatV acc0 = (floatV)(0.0f), acc1 = (floatV)(0.0f), acc2 = (floatV)(0.0f);
    floatV acc3 = (floatV)(0.0f), acc4 = (floatV)(0.0f);

    for (int b = item; b < n_blocks; b += n_items) {
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
        const floatV dtx = fx.v - t.x, dty = fy.v - t.y, dtz = fz.v - t.z;
        const floatV drx = fx.v - r.x, dry = fy.v - r.y, drz = fz.v - r.z;
        floatV nt = sqrt(dtx * dtx + dty * dty + dtz * dtz);
        floatV nr = sqrt(drx * drx + dry * dry + drz * drz);
        const floatV path = nt + nr;
        nt = (nt > 1e-9f) ? nt : (floatV)(1e-9f);
        nr = (nr > 1e-9f) ? nr : (floatV)(1e-9f);
        const floatV idx = path * t.w - sm;
        const intV inside = (idx >= 0.0f) & (idx <= last);
        const floatV i0 = lag_floor(idx, last);
        const floatV w = idx - i0;
        lanes_f li;
        li.v = i0;
        GATHER_PAIRS(row, li, are, aim, bre, bim)
        /* value and slope of the baseband profile, then d/dtau of value * exp(j 2 pi fc tau) */
        const floatV vre = are + w * (bre - are), vim = aim + w * (bim - aim);
        const floatV dre = (bre - are) * deriv.x - vim * deriv.y;
        const floatV dim = (bim - aim) * deriv.x + vre * deriv.y;
        floatV cyc = path * r.w;
        cyc -= RINT(cyc);
        floatV c;
        const floatV s = sincos_2pi(cyc, &c);
        const floatV pre = dre * c - dim * s;   /* s'(tau) = (dre + j dim) e^{j phi} */
        const floatV pim = dre * s + dim * c;
        const floatV gre = vloadV(0, weight_re + v0), gim = vloadV(0, weight_im + v0);
        const floatV rv = inside ? gre * pre + gim * pim : (floatV)(0.0f);
        acc0 += rv;
        acc1 -= rv * (dtx / nt + drx / nr);
        acc2 -= rv * (dty / nt + dry / nr);
        acc3 -= rv * (dtz / nt + drz / nr);
        acc4 += rv * path;
    }
    lanes_f a0, a1, a2, a3, a4;
    a0.v = acc0; a1.v = acc1; a2.v = acc2; a3.v = acc3; a4.v = acc4;
    float s_0 = 0.0f, s_1 = 0.0f, s_2 = 0.0f, s_3 = 0.0f, s_4 = 0.0f;
    for (int l = 0; l < VEC; ++l) {
        s_0 += a0.s[l]; s_1 += a1.s[l]; s_2 += a2.s[l]; s_3 += a3.s[l]; s_4 += a4.s[l];
    }
    __global float *o = out + ((size_t)m * n_items + item) * 5;
    o[0] = s_0; o[1] = s_1; o[2] = s_2; o[3] = s_3; o[4] = s_4;
}
