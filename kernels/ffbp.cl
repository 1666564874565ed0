/* Fast factorized backprojection: leaf sub-images and the merge interpolation.
 *
 * The tables come from clsas/formation/ffbp_tree.py and the twin is
 * clsas/formation/ffbp_numpy.py. A level's sub-images are packed in one buffer of float2
 * (re, im); node n owns samples offset_n .. offset_n + nr nu nv - 1 (range fastest), and each
 * BLOCK of samples belongs to one node (block_node). Node tables, per node:
 *   geom (NG floats): O xyz, e1 xyz, e2 xyz, w xyz, T xyz, R xyz (m), origin r0 u0 v0,
 *                     step dr du dv, 1/step (m or direction cosine)
 *   ints (NI ints):   nr nu nv offset m0 m1 c0 c1
 * Sample (ir, iu, iv) of node n lies at P = O + r (u e1 + v e2 + sqrt(1 - u^2 - v^2) w),
 * r = r0 + ir dr, u = u0 + iu du, v = v0 + iv dv; a direction with u^2 + v^2 >= 1 holds 0.
 * A sub-image at P is  sum_m bp_m(P) exp(-j 2 pi kref ref_n(P)),  ref_n(P) = |P - T| + |P - R|.
 *
 * ffbp_leaf: VEC consecutive samples per work-item as vector lanes (they share a block, so a
 * node and its measurements; the loop is backproject.cl's). ffbp_merge: scalar code, one
 * work-item per sample (each lane would need its own TAPS^3 stencil); PoCL vectorises across
 * the work-group. Needs common.cl (RINT, sincos_2pi, sincos_2pi_1, sincos_small, vsqrt,
 * lerp_pairs) and beam.cl (BEAM_ARGS, BEAM_WEIGHT: with -DBEAM the leaves weight each pair by
 * its two-way beam at the sample's own position, as backproject.cl does at a voxel's; the
 * merges then interpolate beam-weighted sub-images).
 * TAPS (2, 4 or 6) is set with -DTAPS=n. */
#ifndef TAPS
#define TAPS 4
#endif
#define RES 64   /* weight-table entries per sample of stencil position */
#define NG 32
#define NI 8
#define BLOCK 64

inline float floor_1(const float x)
{
    const float r = RINT(x);
    return r > x ? r - 1.0f : r;
}

inline float dist(const float px, const float py, const float pz, __global const float *q)
{
    const float dx = px - q[0], dy = py - q[1], dz = pz - q[2];
    return sqrt(dx * dx + dy * dy + dz * dz);
}

/* The world point of packed sample s of a level; returns its node, or -1 for padding and
 * directions outside the unit disc. */
inline int sample_point(const int s, __global const int *block_node, __global const float *geom,
                        __global const int *ints, float *px, float *py, float *pz)
{
    const int node = block_node[s / BLOCK];
    __global const int *it = ints + node * NI;
    __global const float *g = geom + node * NG;
    const int nr = it[0], nu = it[1], nv = it[2];
    const int k = s - it[3];
    /* x - (x / n) * n rather than %: Oclgrind's uninitialised-value checker cannot follow rem */
    const int iuv = k / nr, ir = k - iuv * nr;
    const int iu = iuv / nv, iv = iuv - iu * nv;
    const float r = g[18] + g[21] * (float)ir;
    const float u = g[19] + g[22] * (float)iu;
    const float v = g[20] + g[23] * (float)iv;
    const float q = 1.0f - u * u - v * v;
    const float sw = q > 0.0f ? sqrt(q) : 0.0f;
    *px = g[0] + r * (u * g[3] + v * g[6] + sw * g[9]);
    *py = g[1] + r * (u * g[4] + v * g[7] + sw * g[10]);
    *pz = g[2] + r * (u * g[5] + v * g[8] + sw * g[11]);
    return (k < nr * nu * nv && q > 0.0f) ? node : -1;
}

/* Stencil of TAPS samples for fractional index f on an axis of n >= TAPS samples: centred
 * (TAPS / 2 at or below f), shifted inwards at the edges; t is f's position in it and *ok
 * says whether f lies on the grid (within half a sample of its ends). */
inline int stencil(float f, const int n, float *t, int *ok)
{
    *ok = (f >= -0.5f) & (f <= (float)n - 0.5f);
    f = f < -1.0f ? -1.0f : (f > (float)n ? (float)n : f);
    int s = (int)floor_1(f) - (TAPS / 2 - 1);
    s = s < 0 ? 0 : s;
    s = s > n - TAPS ? n - TAPS : s;
    *t = f - (float)s;
    return s;
}

/* TAPS weights at stencil position t, linearly interpolated in a table of TAPS * RES + 1 rows
 * (positions -0.5 + i / RES) */
inline void weights(__global const float *table, const float t, float *w)
{
    float x = (t + 0.5f) * (float)RES;
    x = x < 0.0f ? 0.0f : (x > (float)(TAPS * RES) - 1e-3f ? (float)(TAPS * RES) - 1e-3f : x);
    const float xi = floor_1(x);
    const float a = x - xi;
    __global const float *row = table + (int)xi * TAPS;
    for (int j = 0; j < TAPS; ++j) w[j] = row[j] + a * (row[TAPS + j] - row[j]);
}

__kernel void ffbp_leaf(
    __global const float4 *pairs,    /* (n_meas, n_lags) records of the baseband profiles rotated
                                        by the carrier at each sample, as backproject.cl takes
                                        them; tree order, as (re, im, re, im); p[n_lags] = 0    */
    const int n_lags,                /* samples per profile                                     */
    __global const float4 *tx,       /* (n_meas,) speaker xyz, m; w: 1 / (c_m dtau), samples/m  */
    __global const float4 *rx,       /* (n_meas,) microphone xyz, m; w unused                   */
    __global const float *s0,        /* (n_meas,) profile index of zero delay, tau0_m / dtau     */
    const float phi,                 /* 2 pi fc dtau, carrier radians per sample, <= 0.6 pi      */
    __global const float *geom,      /* (n_nodes, NG) leaf tables                               */
    __global const int *ints,        /* (n_nodes, NI)                                           */
    __global const int *block_node,  /* (size / BLOCK,) node of each block                      */
    const float kref,                /* reference cycles per metre of path, f0 / c_ref          */
    __global float2 *out             /* (size,) leaf sub-images                                 */
    BEAM_ARGS)                       /* beam.cl: the beam's buffers with -DBEAM (measurements in
                                        tree order), else nothing                               */
{
    /* VEC consecutive samples per work-item, its vector lanes: they share a BLOCK (BLOCK is a
     * multiple of VEC), so one node and one run of measurements, looped over as bp loops. */
    const int s_first = get_global_id(0) * VEC;
    const int node = block_node[s_first / BLOCK];
    __global const float *g = geom + node * NG;
    __global const int *it = ints + node * NI;
    lanes_f lx, ly, lz, lref;
    lanes_i keep;
    for (int l = 0; l < VEC; ++l) {
        float px, py, pz;
        const int n = sample_point(s_first + l, block_node, geom, ints, &px, &py, &pz);
        keep.s[l] = n >= 0 ? -1 : 0;
        lx.s[l] = px;
        ly.s[l] = py;
        lz.s[l] = pz;
        float cref = kref * (dist(px, py, pz, g + 12) + dist(px, py, pz, g + 15));
        lref.s[l] = cref - RINT(cref);
    }
    const floatV X = lx.v, Y = ly.v, Z = lz.v, CREF = lref.v;
    const float last = (float)(n_lags - 1);
    floatV acc_re = (floatV)(0.0f), acc_im = (floatV)(0.0f);
    for (int m = it[4]; m < it[5]; ++m) {
        const float4 t = tx[m];
        const float4 r = rx[m];
        const floatV dtx = X - t.x, dty = Y - t.y, dtz = Z - t.z;
        const floatV drx = X - r.x, dry = Y - r.y, drz = Z - r.z;
        const floatV path = vsqrt(dtx * dtx + dty * dty + dtz * dtz) + vsqrt(drx * drx + dry * dry + drz * drz);
        const floatV idx = path * t.w - s0[m];
        floatV re, im, f;
        lerp_pairs(pairs + (size_t)m * n_lags, idx, last, &re, &im, &f);
        floatV c;
        floatV sn = sincos_small(phi * (f - 0.5f), &c);   /* the carrier as backproject.cl */
        BEAM_WEIGHT(c, sn, dtx, dty, dtz, drx, dry, drz, m);   /* the pair's beam at the sample */
        acc_re += re * c - im * sn;
        acc_im += re * sn + im * c;
    }
    {   /* less the reference phase, the same for every measurement: one rotation of the sum */
        floatV c;
        const floatV sn = sincos_2pi(-CREF, &c);
        const floatV re = acc_re * c - acc_im * sn;
        acc_im = acc_re * sn + acc_im * c;
        acc_re = re;
    }
    lanes_f ore, oim;
    ore.v = acc_re;
    oim.v = acc_im;
    for (int l = 0; l < VEC; ++l)
        out[s_first + l] = keep.s[l] ? (float2)(ore.s[l], oim.s[l]) : (float2)(0.0f, 0.0f);
}

__kernel void ffbp_merge(
    __global const float2 *vals,     /* children's packed sub-images                            */
    __global const float *cgeom,     /* (n_children, NG) children's tables                      */
    __global const int *cints,       /* (n_children, NI)                                        */
    __global const float *pgeom,     /* (n_parents, NG) parents' tables (unused if cartesian)   */
    __global const int *pints,       /* (n_parents, NI)                                         */
    __global const int *block_node,  /* (size / BLOCK,) parent of each block of samples         */
    __global const float *table_r,   /* (TAPS * RES + 1, TAPS) interpolation weights in range   */
    __global const float *table_a,   /* (TAPS * RES + 1, TAPS) interpolation weights in angle   */
    const float kref,                /* reference cycles per metre of path, f0 / c_ref          */
    const int cartesian,             /* 1: the parent is the voxel grid, every child sums in    */
    const float4 origin,             /* cartesian: centre of voxel (0, 0, 0), m                 */
    const float4 step,               /* cartesian: voxel spacing, m                             */
    const int ny, const int nz,      /* cartesian: voxels along y and z                         */
    const int n_out,                 /* cartesian: voxels                                       */
    const int n_children,            /* cartesian: children (all of them)                       */
    __global float2 *out)            /* (size,) parents' sub-images, or (n_vox_padded,) image   */
{
    const int s = get_global_id(0);
    float px, py, pz, refp = 0.0f;
    int c0 = 0, c1 = n_children, ok;
    if (cartesian) {
        ok = s < n_out;
        const int vox = ok ? s : 0;
        const int yz = vox / nz, iz = vox - yz * nz;
        const int ix = yz / ny, iy = yz - ix * ny;
        px = origin.x + step.x * (float)ix;
        py = origin.y + step.y * (float)iy;
        pz = origin.z + step.z * (float)iz;
    } else {
        const int node = sample_point(s, block_node, pgeom, pints, &px, &py, &pz);
        ok = node >= 0;
        if (ok) {
            __global const float *g = pgeom + node * NG;
            refp = dist(px, py, pz, g + 12) + dist(px, py, pz, g + 15);
            c0 = pints[node * NI + 6];
            c1 = pints[node * NI + 7];
        }
    }
    if (!ok) {
        out[s] = (float2)(0.0f, 0.0f);
        return;
    }
    float acc_re = 0.0f, acc_im = 0.0f;
    for (int c = c0; c < c1; ++c) {
        __global const float *g = cgeom + c * NG;
        __global const int *it = cints + c * NI;
        const float dx = px - g[0], dy = py - g[1], dz = pz - g[2];
        const float rc = sqrt(dx * dx + dy * dy + dz * dz);
        const float inv = 1.0f / (rc > 1e-6f ? rc : 1e-6f);
        const float uc = (dx * g[3] + dy * g[4] + dz * g[5]) * inv;
        const float vc = (dx * g[6] + dy * g[7] + dz * g[8]) * inv;
        const int front = (dx * g[9] + dy * g[10] + dz * g[11]) > 0.0f;
        const int nr = it[0], nu = it[1], nv = it[2];
        float tr, tu, tv;
        int okr, oku, okv;
        const int sr = stencil((rc - g[18]) * g[24], nr, &tr, &okr);
        const int su = stencil((uc - g[19]) * g[25], nu, &tu, &oku);
        const int sv = stencil((vc - g[20]) * g[26], nv, &tv, &okv);
        float wr[TAPS], wu[TAPS], wv[TAPS];
        weights(table_r, tr, wr);
        weights(table_a, tu, wu);
        weights(table_a, tv, wv);
        float sre = 0.0f, sim = 0.0f;
        for (int ju = 0; ju < TAPS; ++ju) {
            for (int jv = 0; jv < TAPS; ++jv) {
                __global const float2 *row = vals + it[3] + ((su + ju) * nv + sv + jv) * nr + sr;
                const float wuv = wu[ju] * wv[jv];
                float lre = 0.0f, lim = 0.0f;
                for (int jr = 0; jr < TAPS; ++jr) {
                    const float2 x = row[jr];
                    lre += wr[jr] * x.x;
                    lim += wr[jr] * x.y;
                }
                sre += wuv * lre;
                sim += wuv * lim;
            }
        }
        const float keep = (front & okr & oku & okv) ? 1.0f : 0.0f;
        float cyc = kref * (dist(px, py, pz, g + 12) + dist(px, py, pz, g + 15) - refp);
        cyc -= RINT(cyc);
        float cs;
        const float sn = sincos_2pi_1(cyc, &cs);
        acc_re += keep * (sre * cs - sim * sn);
        acc_im += keep * (sre * sn + sim * cs);
    }
    out[s] = (float2)(acc_re, acc_im);
}
