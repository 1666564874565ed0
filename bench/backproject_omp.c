/* The C/OpenMP peer of kernels/backproject.cl for `clsas bench`: what a user would write by
 * hand for a CPU. Built at bench time with gcc -O3 -march=native -ffp-contract=fast -fno-math-errno -fopenmp.
 *
 * Same definition as the kernel and its NumPy twin: for each voxel v and measurement m,
 *   path = |v - tx_m| + |v - rx_m|,  idx = path * fs / c - s0_m,
 *   value = lerp(profile_m, idx) * exp(+j 2 pi fc path / c),  zero outside [0, n_lags - 1].
 * float32 throughout; sin/cos of the reduced carrier phase by the same branch-free polynomials
 * as kernels/common.cl. Hand-vectorised with GCC/Clang vector extensions (W = 8 lanes, 16 on
 * AVX-512): each thread owns blocks of 4 W voxels whose accumulators stay in registers, and
 * walks all measurements; the profile is complex interleaved, so the two samples a voxel
 * interpolates are 16 contiguous bytes. OpenMP splits the blocks between threads. */

#include <math.h>
#include <stddef.h>
#include <stdint.h>

/* W lanes of float: 16 where the compiler targets AVX-512, else 8 (AVX2, or SSE pairs) */
#if defined(__AVX512F__)
#define W 16
#else
#define W 8
#endif
typedef float vf __attribute__((vector_size(4 * W)));
typedef int vi __attribute__((vector_size(4 * W)));
#define BLOCK (4 * W)

static inline vf rint_v(vf x) { return (x + 12582912.0f) - 12582912.0f; }
static inline vf sel(vi m, vf a, vf b) { return (vf)((m & (vi)a) | (~m & (vi)b)); }
static inline vf sqrt_v(vf x)
{
    vf r;
    for (int l = 0; l < W; ++l) r[l] = __builtin_sqrtf(x[l]);  /* one vsqrtps with -fno-math-errno */
    return r;
}

void backproject_omp(
    const float *prof,                          /* (n_meas, n_lags + 1, 2) complex profile, 0 last */
    int n_meas, int n_lags,
    const float *tx, const float *rx,           /* (n_meas, 3) positions, m                  */
    const float *s0,                            /* (n_meas,) profile index of zero delay     */
    float samples_per_m, float cycles_per_m,
    const float *px, const float *py, const float *pz, /* (n_vox,) voxel centres, m          */
    int n_vox,
    float *out_re, float *out_im)               /* (n_vox,) image                            */
{
    const float last = (float)(n_lags - 1);
    const int n_blocks = (n_vox + BLOCK - 1) / BLOCK;
#pragma omp parallel for schedule(dynamic, 4)
    for (int b = 0; b < n_blocks; ++b) {
        const int v0 = b * BLOCK;
        vf X[4], Y[4], Z[4], AR[4], AI[4];
        for (int j = 0; j < 4; ++j) {
            for (int l = 0; l < W; ++l) {
                int v = v0 + j * W + l;
                v = v < n_vox ? v : n_vox - 1;
                X[j][l] = px[v]; Y[j][l] = py[v]; Z[j][l] = pz[v];
            }
            AR[j] = (vf){0}; AI[j] = (vf){0};
        }
        for (int m = 0; m < n_meas; ++m) {
            const float tx0 = tx[3 * m], tx1 = tx[3 * m + 1], tx2 = tx[3 * m + 2];
            const float rx0 = rx[3 * m], rx1 = rx[3 * m + 1], rx2 = rx[3 * m + 2];
            const float sm = s0[m];
            const float *row = prof + (size_t)2 * m * (n_lags + 1);
            for (int j = 0; j < 4; ++j) {
                const vf dx = X[j] - tx0, dy = Y[j] - tx1, dz = Z[j] - tx2;
                const vf ex = X[j] - rx0, ey = Y[j] - rx1, ez = Z[j] - rx2;
                const vf path = sqrt_v(dx * dx + dy * dy + dz * dz) + sqrt_v(ex * ex + ey * ey + ez * ez);
                const vf idx = path * samples_per_m - sm;
                const vi inside = (idx >= 0.0f) & (idx <= last);
                vf i0 = rint_v(idx);
                i0 = sel(i0 > idx, i0 - 1.0f, i0);
                i0 = sel(i0 < 0.0f, (vf){0} + 0.0f, i0);
                i0 = sel(i0 > last - 1.0f, (vf){0} + (last - 1.0f), i0);
                const vf w = idx - i0;
                vf re0, im0, re1, im1;
                for (int l = 0; l < W; ++l) {  /* gather: 16 contiguous bytes per lane */
                    const float *p = row + 2 * (int)i0[l];
                    re0[l] = p[0]; im0[l] = p[1]; re1[l] = p[2]; im1[l] = p[3];
                }
                const vf zero = (vf){0};
                const vf re = sel(inside, re0 + w * (re1 - re0), zero);
                const vf im = sel(inside, im0 + w * (im1 - im0), zero);
                vf cyc = path * cycles_per_m;
                cyc -= rint_v(cyc);
                const vf q = rint_v(4.0f * cyc);
                const vf t = 6.28318530718f * (cyc - 0.25f * q);
                const vf t2 = t * t;
                const vf s = t * (1.0f + t2 * (-1.0f / 6.0f + t2 * (1.0f / 120.0f + t2 * (-1.0f / 5040.0f))));
                const vf c = 1.0f + t2 * (-0.5f + t2 * (1.0f / 24.0f + t2 * (-1.0f / 720.0f + t2 * (1.0f / 40320.0f))));
                const vi odd = (q == 1.0f) | (q == -1.0f), isz = q == 0.0f, pos = q > 0.0f;
                const vf cs = sel(odd, sel(pos, -s, s), sel(isz, c, -c));
                const vf sn = sel(odd, sel(pos, c, -c), sel(isz, s, -s));
                AR[j] += re * cs - im * sn;
                AI[j] += re * sn + im * cs;
            }
        }
        for (int j = 0; j < 4; ++j)
            for (int l = 0; l < W; ++l) {
                const int v = v0 + j * W + l;
                if (v < n_vox) { out_re[v] = AR[j][l]; out_im[v] = AI[j][l]; }
            }
    }
}
