/* Transducer beams: the two-way weight of a voxel-measurement pair (clsas/physics/beam.py).
 *
 * Included before a kernel that has the hook lines BEAM_ARGS (end of its argument list) and
 * BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m) (in its measurement loop, scaling the
 * carrier c and s by the weight). Without -DBEAM both expand to nothing: the kernel is the
 * omnidirectional one, bit for bit.
 *
 * The weight is lut_tx(u_tx) * lut_rx(u_rx), u = sin(theta / 2) = sqrt((1 - cos theta) / 2),
 * theta the angle between a transducer's boresight and the direction to the voxel; each table
 * holds beam_n samples uniform in u from 0 to 1, linearly interpolated (the NumPy twin is
 * clsas.physics.beam.pair_weights). With beam_gate > 0 (beam="limited") the weight becomes 1 where it
 * is at least beam_gate and 0 elsewhere. Needs common.cl. */

/* one table at cos theta, lane by lane */
inline floatV beam_lut(__global const float *lut, const int n, const floatV cos_t)
{
    floatV h = 0.5f - 0.5f * cos_t;
    h = (h < 0.0f) ? (floatV)(0.0f) : h;
    h = (h > 1.0f) ? (floatV)(1.0f) : h;
    lanes_f u, out;
    u.v = sqrt(h) * (float)(n - 1);
    for (int l = 0; l < VEC; ++l) {
        int i0 = (int)u.s[l];
        i0 = i0 > n - 2 ? n - 2 : i0;
        const float w = u.s[l] - (float)i0;
        const float a = lut[i0];
        out.s[l] = a + w * (lut[i0 + 1] - a);
    }
    return out.v;
}

inline floatV beam_weight(const floatV dtx, const floatV dty, const floatV dtz, const floatV drx,
                          const floatV dry, const floatV drz, const float4 bt, const float4 br,
                          __global const float *lut, const int n, const float gate)
{
    floatV dd = dtx * dtx + dty * dty + dtz * dtz;
    dd = (dd < 1e-30f) ? (floatV)(1e-30f) : dd;
    const floatV ct = (dtx * bt.x + dty * bt.y + dtz * bt.z) * rsqrt(dd);
    floatV ee = drx * drx + dry * dry + drz * drz;
    ee = (ee < 1e-30f) ? (floatV)(1e-30f) : ee;
    const floatV cr = (drx * br.x + dry * br.y + drz * br.z) * rsqrt(ee);
    const floatV w = beam_lut(lut, n, ct) * beam_lut(lut + n, n, cr);
    if (gate > 0.0f)
        return (w >= gate) ? (floatV)(1.0f) : (floatV)(0.0f);
    return w;
}

#ifdef BEAM
/* beam_dir: (2, n_meas) boresights, speaker rows then microphone rows, unit xyz (w unused);
 * beam_lut: (2, beam_n) tables, speaker then microphone; beam_gate: 0 or the limited level */
#define BEAM_ARGS , __global const float4 *beam_dir, __global const float *beam_lut, const int beam_n, \
                    const int beam_n_meas, const float beam_gate
#define BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m)                                         \
    {                                                                                          \
        const floatV bw_ = beam_weight(dtx, dty, dtz, drx, dry, drz, beam_dir[m],                 \
                                       beam_dir[beam_n_meas + (m)], beam_lut, beam_n, beam_gate); \
        c *= bw_;                                                                              \
        s *= bw_;                                                                              \
    }
#else
#define BEAM_ARGS
#define BEAM_WEIGHT(c, s, dtx, dty, dtz, drx, dry, drz, m)
#endif
