/* Vector helpers shared by the clsas kernels. VEC (4, 8 or 16) is set with -DVEC=n.
 *
 * Hot loops use operators, vector ?: and unions rather than builtins (mad, select, rint,
 * vload): some OpenCL CPU runtimes (PoCL 3.0's wheel among them) call builtins out of line,
 * which costs more than the arithmetic. Every device compiles these forms inline. */
#ifndef VEC
#define VEC 8
#endif
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define floatV CAT(float, VEC)
#define intV CAT(int, VEC)
#define vloadV CAT(vload, VEC)
#define vstoreV CAT(vstore, VEC)
#define as_intV CAT(as_int, VEC)
#define as_floatV CAT(as_float, VEC)

/* a vector and its lanes */
typedef union { floatV v; float s[VEC]; } lanes_f;
typedef union { intV v; int s[VEC]; } lanes_i;

/* round to nearest for |x| < 2^22 (adding 1.5 * 2^23 leaves no fraction bits) */
#define RINT(x) (((x) + 12582912.0f) - 12582912.0f)

/* sin(2 pi c) and cos(2 pi c) for c in [-0.5, 0.5] (cycles already reduced).
 * Quadrant q = rint(4c) in {-2..2}, remainder x = 2 pi (c - q/4) in [-pi/4, pi/4], Taylor
 * polynomials of degree 7 and 8 (error < 4e-7), then a rotation by q quarter turns.
 * Branch-free, so it vectorises on CPUs; the same accuracy on every device. One body for a
 * vector (T = floatV, TI = intV) and for one lane (float, int). */
#define SINCOS_2PI_BODY(T, TI)                                                                       \
    {                                                                                                \
        const T q = RINT(4.0f * c);                                                                  \
        const T x = 6.28318530718f * (c - 0.25f * q);                                                \
        const T x2 = x * x;                                                                          \
        const T s = x * (1.0f + x2 * (-1.0f / 6.0f + x2 * (1.0f / 120.0f + x2 * (-1.0f / 5040.0f)))); \
        const T k = 1.0f + x2 * (-0.5f + x2 * (1.0f / 24.0f + x2 * (-1.0f / 720.0f + x2 * (1.0f / 40320.0f)))); \
        const TI zero = q == 0.0f;                                                                   \
        const TI odd = (q == 1.0f) | (q == -1.0f);                                                   \
        const TI pos = q > 0.0f;                                                                     \
        /* q = 0: (s, k); q = 1: (k, -s); q = -1: (-k, s); q = +-2: (-s, -k) */                      \
        *cos_out = odd ? (pos ? -s : s) : (zero ? k : -k);                                           \
        return odd ? (pos ? k : -k) : (zero ? s : -s);                                               \
    }

inline floatV sincos_2pi(const floatV c, floatV *cos_out) SINCOS_2PI_BODY(floatV, intV)

/* sincos_2pi for one lane (scalar kernels: ffbp.cl) */
inline float sincos_2pi_1(const float c, float *cos_out) SINCOS_2PI_BODY(float, int)

/* sin(x) and cos(x) for |x| <= 0.6 pi, no range reduction: least-squares polynomials of
 * degree 9 and 10 on Chebyshev nodes of that interval (error < 3e-7 in float32). The
 * sub-sample carrier rotation of backproject.cl. */
inline floatV sincos_small(const floatV x, floatV *cos_out)
{
    const floatV x2 = x * x;
    *cos_out = 9.999999981e-01f + x2 * (-4.999999609e-01f + x2 * (4.166653804e-02f
             + x2 * (-1.388733850e-03f + x2 * (2.471691025e-05f + x2 * (-2.541245750e-07f)))));
    return x * (9.999998575e-01f + x2 * (-1.666658625e-01f + x2 * (8.332060710e-03f
             + x2 * (-1.975884462e-04f + x2 * 2.520583304e-06f))));
}

/* sqrt lane by lane with the compiler's own square root, which every clang-based OpenCL
 * compiler inlines (PoCL 3's vector sqrt builtin is an out-of-line call, and every vector
 * register is spilled around it); other compilers, and Oclgrind (whose interpreter lacks the
 * llvm.sqrt intrinsic; the host defines CLSAS_OPENCL_SQRT for it), use the builtin. */
inline floatV vsqrt(const floatV x)
{
#if defined(__clang__) && !defined(CLSAS_OPENCL_SQRT)
    lanes_f u;
    u.v = x;
    for (int l = 0; l < VEC; ++l) u.s[l] = __builtin_sqrtf(u.s[l]);
    return u.v;
#else
    return sqrt(x);
#endif
}

/* floor(idx) clamped to [0, last - 1] (last = n_lags - 1 >= 1), with operators only: the left
 * sample of the linear interpolation at fractional lag idx */
inline floatV lag_floor(const floatV idx, const float last)
{
    floatV i0 = RINT(idx);
    i0 = (i0 > idx) ? i0 - 1.0f : i0;
    i0 = (i0 < 0.0f) ? (floatV)(0.0f) : i0;
    return (i0 > last - 1.0f) ? (floatV)(last - 1.0f) : i0;
}


/* Gather VEC float4 (a_re, a_im, b_re, b_im) records at lane indices li (lanes_f holding
 * integral floats) from `src` into four planar vectors, with constructors and .even/.odd
 * swizzles (no private-memory round trip). */
#define G4(src, li, l) (src)[(int)(li).s[l]]
/* lanes 4j .. 4j+3 as two float8 of (a_re, a_im, b_re, b_im) records, split into
 * e = (a_re, b_re, ...) and o = (a_im, b_im, ...). (One float16 of four records is a little
 * faster on PoCL but crashes Oclgrind 19.10's uninitialised-value plugin.) */
#define QUAD(src, li, j, e, o)                                                              \
    const float8 qa##j = (float8)(G4(src, li, 4 * j), G4(src, li, 4 * j + 1));               \
    const float8 qb##j = (float8)(G4(src, li, 4 * j + 2), G4(src, li, 4 * j + 3));           \
    const float8 e = (float8)(qa##j.even, qb##j.even), o = (float8)(qa##j.odd, qb##j.odd)
#if VEC == 4
#define GATHER_PAIRS(src, li, are, aim, bre, bim)                                           \
    QUAD(src, li, 0, e0, o0);                                                               \
    const floatV are = e0.even, bre = e0.odd, aim = o0.even, bim = o0.odd;
#elif VEC == 8
#define GATHER_PAIRS(src, li, are, aim, bre, bim)                                           \
    QUAD(src, li, 0, e0, o0);                                                               \
    QUAD(src, li, 1, e1, o1);                                                               \
    const floatV are = (float8)(e0.even, e1.even), bre = (float8)(e0.odd, e1.odd);          \
    const floatV aim = (float8)(o0.even, o1.even), bim = (float8)(o0.odd, o1.odd);
#elif VEC == 16
#define GATHER_PAIRS(src, li, are, aim, bre, bim)                                           \
    QUAD(src, li, 0, e0, o0);                                                               \
    QUAD(src, li, 1, e1, o1);                                                               \
    QUAD(src, li, 2, e2, o2);                                                               \
    QUAD(src, li, 3, e3, o3);                                                               \
    const floatV are = (float16)(e0.even, e1.even, e2.even, e3.even);                      \
    const floatV bre = (float16)(e0.odd, e1.odd, e2.odd, e3.odd);                          \
    const floatV aim = (float16)(o0.even, o1.even, o2.even, o3.even);                      \
    const floatV bim = (float16)(o0.odd, o1.odd, o2.odd, o3.odd);
#else
#error "VEC must be 4, 8 or 16"
#endif

/* The baseband profile `row` ((p[k], p[k+1]) records, GATHER_PAIRS's layout) linearly
 * interpolated at fractional lags idx, lane by lane; 0 outside [0, last] (last = n_lags - 1).
 * What backproject.cl and ffbp.cl's leaves read per voxel-measurement pair; also
 * returns the interpolation weight idx - floor(idx) (floor clamped to [0, last - 1]), 0.5 in
 * the lanes outside [0, last]. */
inline void lerp_pairs(__global const float4 *row, const floatV idx, const float last, floatV *re, floatV *im,
                       floatV *w_out)
{
    const intV inside = (idx >= 0.0f) & (idx <= last);
    lanes_f li;
    li.v = lag_floor(idx, last);
    const floatV w = idx - li.v;
    GATHER_PAIRS(row, li, are, aim, bre, bim)
    *re = inside ? are + w * (bre - are) : (floatV)(0.0f);
    *im = inside ? aim + w * (bim - aim) : (floatV)(0.0f);
    *w_out = inside ? w : (floatV)(0.5f); /* in [0, 1] where the sample counts */
}
