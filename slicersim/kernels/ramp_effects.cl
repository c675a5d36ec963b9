/*
 * ramp_effects.cl: charge-domain detector effects of the MACC samplers of ramp.cl
 * (included by ramp.cl when built with -DRAMP_EFFECTS=1; not a program by itself).
 *
 * With RAMP_EFFECTS the two samplers keep every random draw of the plain build
 * (same counters, same paths) and add, per pixel:
 *   deposits     extra charge [e-] at given frames (cosmic rays, persistence): a
 *                CSR list per block pixel (dep_start[i] .. dep_start[i+1]) of
 *                (frame counted from the reset, electrons), sorted by frame, added
 *                to the accumulated charge of that frame before full-well clipping;
 *   nonlinearity the read value of accumulated charge Q is
 *                R(Q) = Q + Q*Q*(a2 + a3*Q)  [e-]  (per-pixel a2, a3; use_nl = 0: R = Q)
 * and store the group mean of R over the m reads as real (gmean, e-; float64, or float32 with -DSINGLE) with the
 * charge-saturation flag, leaving read noise, IPC, correlated noise and
 * digitisation to ramp_readout.cl.  Sparse windows whose pixel has a deposit in
 * the window (or every window when use_nl) are summed read by read:
 *   sum_j R(min(full_well, (before + c_j) + d_j)),
 * c_j = number of Poisson events at positions <= j, d_j = deposits at positions <= j
 * (added in list order); other windows keep the plain closed form m*before + seen.
 * The NumPy twin is slicersim/backends/ramp_effects.py; both agree bit for bit.
 */
#define RAMP_POS_MAX 8            /* event positions kept per window (later ones recomputed) */
#ifdef SINGLE
#define RAMP_NO_DEPOSIT 1e30f      /* beyond any frame number */
#else
#define RAMP_NO_DEPOSIT 1e300
#endif

RAMP_INLINE rng_real nl_read(const rng_real q, const rng_real a2, const rng_real a3)
{
    return q + q * q * (a2 + a3 * q);
}

/* per-lane values of a per-pixel array */
RAMP_INLINE rng_real load_lanes(__global const real *restrict a, const uint *idx)
{
    real v[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l)
        v[l] = a[idx[l]];
#if RNG_VW == 1
    return v[0];
#else
    return RNG_PASTE(vload, RNG_SUFFIX)(0, v);
#endif
}

RAMP_INLINE rng_real lanes_from(const real *v)
{
#if RNG_VW == 1
    return v[0];
#else
    return RNG_PASTE(vload, RNG_SUFFIX)(0, v);
#endif
}

/* cursor of each lane in its deposit list; returns the frame of each lane's next deposit */
RAMP_INLINE rng_real deposit_cursor(__global const uint *restrict dep_start, __global const int *restrict dep_frame,
                                      const uint *idx, uint *dp, uint *de)
{
    real nf[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l) {
        dp[l] = dep_start[idx[l]];
        de[l] = dep_start[idx[l] + 1];
        nf[l] = dp[l] < de[l] ? (real)dep_frame[dp[l]] : RAMP_NO_DEPOSIT;
    }
    return lanes_from(nf);
}

/* Sum of the deposits of each lane at frames < frame_end (list order, from 0.0); advances the
 * cursors (ws: each lane's first deposit consumed) and returns the next deposit frames in *next. */
RAMP_INLINE rng_real take_deposits(__global const int *restrict dep_frame, __global const real *restrict dep_e,
                                     const int frame_end, uint *dp, const uint *de, uint *ws, rng_real *next)
{
    real add[RNG_VW], nf[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l) {
        real a = 0.0;
        ws[l] = dp[l];
        while (dp[l] < de[l] && dep_frame[dp[l]] < frame_end) {
            a = a + dep_e[dp[l]];
            dp[l] += 1u;
        }
        add[l] = a;
        nf[l] = dp[l] < de[l] ? (real)dep_frame[dp[l]] : RAMP_NO_DEPOSIT;
    }
    *next = lanes_from(nf);
    return lanes_from(add);
}

/* Read-by-read sum of a sparse window: sum_j R(min(full_well, (before + c_j) + d_j)). */
RAMP_INLINE rng_real window_read_sum(const rng_real before, const rng_real K, const rng_real pos0,
                                       const rng_real *posk, const int g, const int w, const int m, const int f0,
                                       const real full_well, const rng_ulong pixv, const uint stream,
                                       const uint k0, const uint k1, const int any_dep, const uint *ws,
                                       const uint *dp, __global const int *restrict dep_frame,
                                       __global const real *restrict dep_e, const rng_real a2,
                                       const rng_real a3, const int use_nl)
{
    rng_real total = 0.0;
    if (!any_dep && !RAMP_ANY(K > 1.0)) {
        /* no deposit and at most one event per lane (most dark windows): the read values take two
         * levels, R(clip(before + 0)) before the event and R(clip(before + 1)) from it on: the same
         * values and sums as the loop below, with R evaluated twice instead of m times */
        rng_real q0 = before + 0.0, q1 = before + 1.0;
        q0 = RNG_SELECT(q0, (rng_real)full_well, q0 >= full_well);
        q1 = RNG_SELECT(q1, (rng_real)full_well, q1 >= full_well);
        const rng_real r0 = use_nl ? nl_read(q0, a2, a3) : q0, r1 = use_nl ? nl_read(q1, a2, a3) : q1;
        for (int j = 0; j < m; ++j)
            total = total + RNG_SELECT(r0, r1, (K > 0.0) && (pos0 <= (real)j));
        return total;
    }
    for (int j = 0; j < m; ++j) {
        rng_real cj = RNG_SELECT((rng_real)0.0, (rng_real)1.0, (K > 0.0) && (pos0 <= (real)j));
        for (int k = 1; RAMP_ANY((real)k < K); ++k) {
            const rng_real pos = k < RAMP_POS_MAX ? posk[k] : event_position(g, k, w, pixv, stream, k0, k1);
            cj = RNG_SELECT(cj, cj + 1.0, ((real)k < K) && (pos <= (real)j));
        }
        rng_real charge = before + cj;
        if (any_dep) {
            real dj[RNG_VW];
            for (int l = 0; l < RNG_VW; ++l) {
                real a = 0.0;
                for (uint q = ws[l]; q < dp[l]; ++q)
                    if (dep_frame[q] - f0 <= j)
                        a = a + dep_e[q];
                dj[l] = a;
            }
            charge = charge + lanes_from(dj);
        }
        charge = RNG_SELECT(charge, (rng_real)full_well, charge >= full_well);
        total = total + (use_nl ? nl_read(charge, a2, a3) : charge);
    }
    return total;
}

/* group mean of the read values [e-] and the sticky charge-saturation flag of group g
 * (one vector store each where the lanes are consecutive pixels) */
RAMP_INLINE void store_mean(const int g, const rng_real sum, const ramp_mask sat, const int m,
                            __global real *restrict gmean, __global uchar *restrict gdq, const uint *idx,
                            const int contiguous, const size_t npix)
{
    __global real *gm = gmean + (size_t)g * npix;
    __global uchar *gq = gdq + (size_t)g * npix;
#if RNG_VW > 1
    if (contiguous) {
        RNG_PASTE(vstore, RNG_SUFFIX)(sum / (real)m, 0, gm + idx[0]);
        RAMP_VSTORE(RAMP_FLAG(sat), gq + idx[0]);
        return;
    }
#endif
    real v[RNG_VW];
    uchar q[RNG_VW];
#if RNG_VW == 1
    v[0] = sum / (real)m;
    q[0] = RAMP_FLAG(sat);
#else
    RNG_PASTE(vstore, RNG_SUFFIX)(sum / (real)m, 0, v);
    RAMP_VSTORE(RAMP_FLAG(sat), q);
#endif
    for (int l = 0; l < RNG_VW; ++l) {
        gm[idx[l]] = v[l];
        gq[idx[l]] = q[l];
    }
}
