/* The carrier records of backproject.cl, made on the device from compressed profiles.
 *
 * The definition (clsas/formation/bp_numpy.py: carrier_records, which calls upsample):
 *   p_k      = profile sample k, k < n_data; 0 for n_data <= k (zero-padded to n_lags = L)
 *   fine_j   = (1 - i/up) p_k + (i/up) p_{k+1},  j = k up + i, 0 <= i < up, j < n_rec
 *              (the profile linearly upsampled up times; n_rec = (L - 1) up + 1, fine_{n_rec} = 0)
 *   R_mj     = rot_j rot0_m,  rot_j = exp(j 2 pi (fc dtau' (j + 1/2) mod 1)),
 *              rot0_m = exp(j 2 pi (fc dtau' s0_m mod 1)),  dtau' = dtau / up, s0_m = tau0_m / dtau'
 *   record j = (fine_j R_mj, fine_{j+1} R_mj)
 * rot and rot0 are reduced to a turn in double precision on the host (rot once per shape, rot0
 * one value per measurement), so that no carrier phase is formed in float32 here.
 *
 * Each work-item makes VEC consecutive records of one measurement (global size
 * (ceil(n_rec / VEC), n_meas)); records past n_rec are not written.
 *
 * Built with -DROW_MAP, record row m is made from row row_of[m] of prof (another order of the
 * same rows: FFBP's tree order); rot0 is then given in the records' order. */

/* fine_j of the row `p` (n_data samples), as above */
inline float2 fine_sample(__global const float2 *p, const int n_data, const int up, const float inv_up, const int j)
{
    const int k = j / up;
    const int i = j - k * up;
    const float w = (float)i * inv_up;
    const float2 a = k < n_data ? p[k] : (float2)(0.0f);
    const float2 b = k + 1 < n_data ? p[k + 1] : (float2)(0.0f);
    return (1.0f - w) * a + w * b;
}

inline float2 cmul(const float2 a, const float2 b)
{
    return (float2)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

__kernel void carrier_records(
    __global const float2 *prof,     /* (n_meas, stride) baseband profiles (re, im); the first
                                        n_data samples of each row are read                    */
    const int stride,                /* complex samples from one row of prof to the next        */
    const int n_data,                /* samples of a row that hold data (the rest is zero)      */
    const int up,                    /* upsampling factor, >= 1                                 */
    const int n_rec,                 /* records per measurement: (n_lags - 1) up + 1            */
    __global const float2 *rot,      /* (n_rec,) carrier at the middle of record j, R's j part  */
    __global const float2 *rot0,     /* (n_meas,) carrier at each profile's zero delay          */
    __global float4 *pairs           /* (n_meas, n_rec) records (q_j, r_j) as (re, im, re, im)  */
#ifdef ROW_MAP
    , __global const int *row_of     /* (n_meas,) the row of prof record row m is made from     */
#endif
    )
{
    const int j0 = get_global_id(0) * VEC;
    const int m = get_global_id(1);
#ifdef ROW_MAP
    __global const float2 *p = prof + (size_t)row_of[m] * stride;
#else
    __global const float2 *p = prof + (size_t)m * stride;
#endif
    const float inv_up = 1.0f / (float)up;
    const float2 r0 = rot0[m];
    for (int l = 0; l < VEC && j0 + l < n_rec; ++l) {
        const int j = j0 + l;
        const float2 R = cmul(rot[j], r0);
        const float2 q = cmul(fine_sample(p, n_data, up, inv_up, j), R);
        const float2 r = j + 1 < n_rec ? cmul(fine_sample(p, n_data, up, inv_up, j + 1), R) : (float2)(0.0f);
        pairs[(size_t)m * n_rec + j] = (float4)(q, r);
    }
}
