/* A focus metric of a complex image on the device, and its weight per voxel.
 *
 * The image I(v) is the complex64 image backproject.cl leaves on the device (-DCOMPLEX_IMAGE).
 * With p(v) = scale |I(v)|^2 (``scale`` keeps the sums in float's range; every metric below is
 * unchanged by it):
 *
 *   focus_moments  per work-item partial sums (max |I|^2 unscaled, sum p, sum p^2, sum p log p)
 *                  that the host adds in double: the metric needs the whole image's sums
 *   focus_weight   G(v) = I(v) (a f(p(v)) + b), f(p) = p (-DENTROPY absent) or log p
 *                  (-DENTROPY; G = 0 where p = 0), the two numbers from the host's sums,
 *                  written as two float planes for focus_gradient (autofocus.cl); padding 0
 *
 * See clsas/focus/metric_numpy.py, the specification. Work-item i owns the voxel blocks i,
 * i + n_items, ... of VEC voxels each; no work-item reads what another writes. */

__kernel void focus_moments(
    __global const float2 *image,  /* (n_vox,) complex image                                  */
    const int n_vox,               /* voxels                                                  */
    const float scale,             /* p = scale |I|^2                                         */
    __global float4 *partial)      /* (n_items,) (max |I|^2, sum p, sum p^2, sum p log p)    */
{
    const int item = get_global_id(0);
    const int n_items = get_global_size(0);
    float4 acc = (float4)(0.0f);
    for (int v0 = item * VEC; v0 < n_vox; v0 += n_items * VEC) {
        for (int k = 0; k < VEC; k++) {
            const int v = v0 + k;
            if (v < n_vox) {
                const float2 x = image[v];
                const float q = x.x * x.x + x.y * x.y;
                const float p = scale * q;
                acc.x = fmax(acc.x, q);
                acc.y += p;
                acc.z += p * p;
                acc.w += p > 0.0f ? p * log(p) : 0.0f;
            }
        }
    }
    partial[item] = acc;
}

__kernel void focus_weight(
    __global const float2 *image,  /* (n_vox,) complex image                                  */
    const int n_vox,               /* voxels                                                  */
    const int n_pad,               /* length of the weight planes (voxels and padding)        */
    const float scale,             /* p = scale |I|^2                                         */
    const float a,                 /* G = I (a f(p) + b)                                      */
    const float b,
    __global float *weight_re,     /* (n_pad,) Re G                                           */
    __global float *weight_im)     /* (n_pad,) Im G                                           */
{
    const int item = get_global_id(0);
    const int n_items = get_global_size(0);
    for (int v0 = item * VEC; v0 < n_pad; v0 += n_items * VEC) {
        for (int k = 0; k < VEC; k++) {
            const int v = v0 + k;
            if (v >= n_pad)
                break;
            float2 g = (float2)(0.0f);
            if (v < n_vox) {
                const float2 x = image[v];
                const float p = scale * (x.x * x.x + x.y * x.y);
#ifdef ENTROPY
                const float f = p > 0.0f ? a * log(p) + b : 0.0f;
#else
                const float f = a * p + b;
#endif
                g = x * f;
            }
            weight_re[v] = g.x;
            weight_im[v] = g.y;
        }
    }
}
