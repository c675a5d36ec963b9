/*
 * ramp_fit.cl: up-the-ramp fit of MACC group means, one work item per VW consecutive pixels (lanes of
 * vector types, -DVW=1|2|4|8|16: CPUs vectorise only explicit vectors), all integrations.
 *
 * Input (flat block of npix pixels, group-major): sci (nints, NGROUPS, npix) [DN] as ushort (raw
 * ADU) or double (corrected DN, -DSCI_DOUBLE=1), GROUPDQ (same shape, JWST bits), PIXELDQ (npix).
 * With D_j = (g_{j+1} - g_j) / gain [e-] the differences of consecutive group means:
 *
 * 1. saturation: a group flagged SATURATED or reading >= satlim, and every later group, is
 *    SATURATED; a group is usable unless SATURATED or DO_NOT_USE; difference j is used when
 *    groups j and j+1 are usable, group j+1 carries no JUMP_DET flag and D_j is finite;
 * 2. jumps (jump_thr > 0): while >= JUMP_MIN_DIFFS differences are used, the one farthest from
 *    their median med is a jump if |D_j - med| > jump_thr * sigma, with
 *    sigma^2 = 2 sg2 + (max(med, 0) / tau) * (tau - 2 c)   (exact variance of a difference);
 *    it is dropped and JUMP_DET set on group j+1 (find_jump: no sort of all differences);
 * 3. runs of used differences are the segments; the OLS slope of a run of L differences is
 *    sum_p w_p D_p / (tau sum_p w_p) with w_p = p (L + 1 - p), p = 1..L (unweighted least squares
 *    of its L + 1 group means), summed in closed form: sum w = L(L+1)(L+2)/6, sum w^2 =
 *    L(L+1)(L+2)(L^2+2L+2)/30, sum (w_p - w_{p-1})^2 = L(L+1)(L+2)/3; all runs of all integrations
 *    combined with the read-noise weights L(L+1)(L+2) (stcal's combination) give the OLS rate
 *    lam0 = sum P / (tau sum S), clipped at 0: the rate in the covariance;
 * 4. WEIGHTING 1 = OLS (as 3); WEIGHTING 0 = GLS: w = T^-1 1 per run, T the covariance of its
 *    differences, tridiagonal Toeplitz: diagonal a = 2 sg2 + lam0 (tau - 2c), off-diagonal
 *    b = lam0 c - sg2, c = tframe (m^2 - 1) / (6 m); solved through leading minors (pass 2);
 * 5. rate = sum P / (tau sum S)  [e-/s]; variance = sum_run w^T T w / (tau sum S)^2 split into
 *    read  sg2 sum_p (w_p - w_{p-1})^2  and Poisson  lam0 ((tau - 2c) sum w^2 + 2c sum w_p w_{p+1}).
 *
 * Output: rate_out, var_out, vpois_out, vread_out (npix each) = rate [e-/s], variance, Poisson
 * variance, read variance [e-^2/s^2] (four arrays, so that a caller's rate images are written in place);
 * dq = PIXELDQ | SATURATED (any group) | JUMP_DET (any jump) | DO_NOT_USE (no used difference,
 * rate NaN); njump = jumps (detected and flagged on input); gdq_out = GROUPDQ with SATURATED and
 * JUMP_DET set (WANT_GDQ); bits: scratch (nints, NWORDS, npix) of the used flags between the passes
 * (GLS, nints > 1).  Build with -DNGROUPS=n -DWEIGHTING=0|1 -DSCI_DOUBLE=0|1 -DWANT_GDQ=0|1 -DVW=w.
 * Lanes: every step is computed for all VW pixels and kept per lane by masks (select), in the
 * scalar operation order, so each lane's result does not depend on VW; the jump search (data-
 * dependent loops) runs lane by lane, only for lanes whose range of differences fails the quick
 * test.  The last work item's lanes past npix repeat the last pixel and are not stored.
 * NumPy twin: slicersim/backends/ramp_fit.py (fit_block_numpy), same operation order.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
#include "vector_types.cl"

#ifndef NGROUPS
#error "build with -DNGROUPS=<groups per integration>"
#endif
#ifndef WEIGHTING
#define WEIGHTING 0
#endif
#ifndef SCI_DOUBLE
#define SCI_DOUBLE 0
#endif

#define NDIFF (NGROUPS - 1)
#define NWORDS ((NDIFF + 63) / 64)
#ifndef WANT_GDQ
#define WANT_GDQ 1
#endif
#define DQ_DNU 1u
#define DQ_SAT 2u
#define DQ_JUMP 4u
#define JUMP_MIN_DIFFS 3

#if SCI_DOUBLE
#define SCI_NAME double
#else
#define SCI_NAME ushort
#endif
typedef SCI_NAME sci_t;

/* lanes: VT(type) the vector of VW values, MASK(comparison) its -1 / 0 long mask */
#if VW == 1
#define VT(t) t
#define MASK(c) (-(long)(c))
#else
#define VT(t) CAT(t, VW)
#define MASK(c) CONVERT_V(long, c)
#endif
typedef VT(double) vdouble;
typedef VT(long) vlong;
typedef VT(int) vint;
typedef VT(uint) vuint;
typedef VT(uchar) vuchar;
typedef VT(ulong) vulong;
typedef VT(SCI_NAME) vsci;
#define ZERO ((vdouble)(0.0))
#define ONE ((vdouble)(1.0))

/* loads and stores of the VW lanes at p, nvalid of them valid: a short last work item repeats its
 * last pixel on loads and stores only its valid lanes */
#define DEFINE_LOAD(T, V, name)                                                                    \
    inline V name(__global const T *p, const uint nvalid)                                          \
    {                                                                                              \
        if (nvalid == VW)                                                                          \
            return VLOAD(0, p);                                                                    \
        T t[VW];                                                                                   \
        for (uint l = 0; l < VW; ++l)                                                              \
            t[l] = p[l < nvalid ? l : nvalid - 1];                                                 \
        return VLOAD(0, t);                                                                        \
    }
#define DEFINE_STORE(T, V, name)                                                                   \
    inline void name(const V v, __global T *p, const uint nvalid)                                  \
    {                                                                                              \
        if (nvalid == VW) {                                                                        \
            VSTORE(v, 0, p);                                                                       \
            return;                                                                                \
        }                                                                                          \
        T t[VW];                                                                                   \
        VSTORE(v, 0, t);                                                                           \
        for (uint l = 0; l < nvalid; ++l)                                                          \
            p[l] = t[l];                                                                           \
    }
DEFINE_LOAD(sci_t, vsci, load_sci)
DEFINE_LOAD(uchar, vuchar, load_uchar)
DEFINE_LOAD(uint, vuint, load_uint)
DEFINE_LOAD(ulong, vulong, load_ulong)
DEFINE_STORE(uchar, vuchar, store_uchar)
DEFINE_STORE(uint, vuint, store_uint)
DEFINE_STORE(int, vint, store_int)
DEFINE_STORE(ulong, vulong, store_ulong)
DEFINE_STORE(double, vdouble, store_double)

/* Jump test of the used D (nv of them, in [dmin, dmax]): 1 when the one farthest from their
 * median med = 0.5 (s[(nv-1)/2] + s[nv/2]) (s: sorted) lies more than jump_thr sigma(med) away,
 * with med in *med_out; 0 otherwise.  That one is dmin or dmax.  A bracket [lo, hi] of both order
 * statistics (count(D < lo) = below kept exact) is halved by counting; the test is decided as soon
 * as the bracket bounds it (IEEE rounding is monotone, so the bound is exact), else the <= 8
 * values left in the bracket are sorted by insertion in A and the median is exact. */
inline int find_jump(const double *D, const uchar *used, const int nv, const double dmin, const double dmax,
                     const double sg2, const double tau, const double pois_diag, const double jump_thr,
                     double *A, double *med_out)
{
    const int klo = (nv - 1) >> 1, khi = nv >> 1;
    double lo = dmin, hi = dmax;
    int below = 0, upto = nv;                    /* count(D < lo), count(D <= hi) */
    for (;;) {
        if (!(fmax(dmax - lo, hi - dmin) > jump_thr * sqrt(2.0 * sg2 + (fmax(lo, 0.0) / tau) * pois_diag)))
            return 0;
        if (upto - below <= 8)
            break;
        const double mid = 0.5 * (lo + hi);
        if (!(mid > lo && mid < hi))
            break;
        int c = 0, ce = 0;
        for (int j = 0; j < NDIFF; ++j) {
            c += used[j] && D[j] < mid;
            ce += used[j] && D[j] <= mid;
        }
        if (c > khi) {
            hi = mid;
            upto = ce;
        } else if (c <= klo) {
            lo = mid;
            below = c;
        } else {
            break;
        }
    }
    int m = 0;
    for (int j = 0; j < NDIFF; ++j) {
        if (used[j] && D[j] >= lo && D[j] <= hi) {
            const double v = D[j];
            int at = m++;
            while (at > 0 && A[at - 1] > v) {
                A[at] = A[at - 1];
                --at;
            }
            A[at] = v;
        }
    }
    const double med = 0.5 * (A[klo - below] + A[khi - below]);
    *med_out = med;
    return fmax(dmax - med, med - dmin) > jump_thr * sqrt(2.0 * sg2 + (fmax(med, 0.0) / tau) * pois_diag);
}

/* D [e-] of integration `base` and its used masks from the bits of pass 1 (lanes) */
inline void reload(__global const sci_t *sci, __global const ulong *bits, const size_t base, const size_t bbase,
                   const uint npix, const uint nvalid, const double inv_gain, double *D, long *U)
{
    vdouble prev = CONVERT_V(double, load_sci(sci + base, nvalid));
    for (int k = 1; k < NGROUPS; ++k) {
        const vdouble x = CONVERT_V(double, load_sci(sci + base + (size_t)k * npix, nvalid));
        VSTORE((x - prev) * inv_gain, 0, D + (k - 1) * VW);
        prev = x;
    }
    for (int w = 0; w < NWORDS; ++w) {
        const vulong word = load_ulong(bits + bbase + (size_t)w * npix, nvalid);
        for (int j = 64 * w; j < NDIFF && j < 64 * (w + 1); ++j)
            VSTORE(-CONVERT_V(long, (word >> (ulong)(j - 64 * w)) & (ulong)1), 0, U + j * VW);
    }
}

/* the jump search of lane l of D, U, F (pass 1): jumps dropped from U and flagged in F; returns
 * their number.  Dl, used, A: scratch of NDIFF values. */
inline int lane_jumps(const double *D, long *U, uchar *F, const int l, const double sg2, const double tau,
                      const double pois_diag, const double jump_thr, double *Dl, uchar *used, double *A)
{
    int nv = 0, found = 0;
    double dmin = INFINITY, dmax = -INFINITY, med;
    for (int j = 0; j < NDIFF; ++j) {
        Dl[j] = D[j * VW + l];
        used[j] = U[j * VW + l] != 0;
        if (used[j]) {
            ++nv;
            dmin = fmin(dmin, Dl[j]);
            dmax = fmax(dmax, Dl[j]);
        }
    }
    while (nv >= JUMP_MIN_DIFFS && find_jump(Dl, used, nv, dmin, dmax, sg2, tau, pois_diag, jump_thr, A, &med)) {
        int jbest = -1;
        double dbest = -1.0;
        for (int j = 0; j < NDIFF; ++j) {
            const double dev = used[j] ? fabs(Dl[j] - med) : -1.0;
            if (dev > dbest) {
                dbest = dev;
                jbest = j;
            }
        }
        used[jbest] = 0;
        U[jbest * VW + l] = 0;
        F[(jbest + 1) * VW + l] |= DQ_JUMP;
        ++found;
        nv = 0;
        dmin = INFINITY;
        dmax = -INFINITY;
        for (int j = 0; j < NDIFF; ++j) {
            if (used[j]) {
                ++nv;
                dmin = fmin(dmin, Dl[j]);
                dmax = fmax(dmax, Dl[j]);
            }
        }
    }
    return found;
}

#ifndef SORT_MAX
#define SORT_MAX 64
#endif
#if NDIFF >= JUMP_MIN_DIFFS && NDIFF <= SORT_MAX
/* Lanes that use every difference (mask `all`) and certainly have no jump: their D sorted at once
 * (Batcher's odd-even merge network on the lanes, fmin/fmax, unrolled), the median med as
 * find_jump's (0.5 (s[(n-1)/2] + s[n/2])) and its test; returns the lanes that do not pass it.  A lane with a
 * non-finite D is left to find_jump (fmin/fmax drop NaN). */
inline vlong no_jump_sorted(const double *D, const vdouble dmin, const vdouble dmax, const double sg2,
                            const double tau, const double pois_diag, const double jump_thr, const vlong all)
{
    vdouble s[NDIFF], total = ZERO;
#pragma unroll
    for (int j = 0; j < NDIFF; ++j) {
        s[j] = VLOAD(0, D + j * VW);
        total = total + s[j];
    }
#pragma unroll
    for (int p = 1; p < NDIFF; p <<= 1)
#pragma unroll
        for (int k = p; k >= 1; k >>= 1)
#pragma unroll
            for (int j = k % p; j <= NDIFF - 1 - k; j += 2 * k)
#pragma unroll
                for (int i = 0; i <= min(k - 1, NDIFF - j - k - 1); ++i)
                    if ((i + j) / (2 * p) == (i + j + k) / (2 * p)) {
                        const vdouble a = s[i + j], b = s[i + j + k];
                        s[i + j] = fmin(a, b);
                        s[i + j + k] = fmax(a, b);
                    }
    const vdouble med = 0.5 * (s[(NDIFF - 1) >> 1] + s[NDIFF >> 1]);
    const vlong jump = MASK(fmax(dmax - med, med - dmin) > jump_thr * sqrt(2.0 * sg2 + (fmax(med, 0.0) / tau) * pois_diag));
    return all & MASK(isfinite(total)) & ~jump;
}
#endif

__kernel void ramp_fit(__global const sci_t *sci, __global const uchar *gdq_in, __global uchar *gdq_out,
                       __global ulong *bits, __global const uint *pixeldq, __global double *rate_out,
                       __global double *var_out, __global double *vpois_out, __global double *vread_out,
                       __global uint *dq_out, __global int *njump_out, const uint npix, const uint nints,
                       const double inv_gain, const double sg2, const double tau, const double ccorr,
                       const double satlim, const double jump_thr)
{
    const size_t p = get_global_id(0) * VW;
    if (p >= npix)
        return;
    const uint nvalid = (uint)min((size_t)VW, (size_t)npix - p);
    double D[NDIFF * VW], A[NDIFF * VW], B[NDIFF * VW], C[NDIFF * VW];
    long U[NDIFF * VW];                              /* used: -1 / 0 per lane */
    uchar F[NGROUPS * VW];
    double Dl[NDIFF];
    uchar usedl[NDIFF];
    const double pois_diag = tau - 2.0 * ccorr;     /* Poisson variance of a difference per e-/s [s] */
    vint njump = 0;
    vlong anysat = 0;
    vdouble P = ZERO, S = ZERO, W2 = ZERO, Q = ZERO, WW;

    /* pass 1: saturation, jumps, OLS sums (closed forms per run of L differences) */
    for (uint i = 0; i < nints; ++i) {
        const size_t base = (size_t)i * NGROUPS * npix + p;
        vlong sat = 0, usable_prev = 0, allused = -1;
        vdouble prev = ZERO, dmin = (vdouble)(INFINITY), dmax = (vdouble)(-INFINITY);
        vint nv = 0;
        for (int k = 0; k < NGROUPS; ++k) {
            const size_t at = base + (size_t)k * npix;
            vuchar f = load_uchar(gdq_in + at, nvalid);
            const vdouble x = CONVERT_V(double, load_sci(sci + at, nvalid));
            sat |= MASK((f & (uchar)DQ_SAT) != (uchar)0) | MASK(x >= satlim);
            f |= CONVERT_V(uchar, sat) & (uchar)DQ_SAT;
            const vlong usable = MASK((f & (uchar)(DQ_SAT | DQ_DNU)) == (uchar)0);
            if (k > 0) {
                const vdouble d = (x - prev) * inv_gain;
                const vlong both = usable_prev & usable;
                const vlong flagged = MASK((f & (uchar)DQ_JUMP) != (uchar)0);
                njump -= CONVERT_V(int, both & flagged);
                const vlong u = both & ~flagged & MASK(isfinite(d));     /* NaN / inf: never used */
                VSTORE(d, 0, D + (k - 1) * VW);
                VSTORE(u, 0, U + (k - 1) * VW);
                nv -= CONVERT_V(int, u);
                allused &= u;
                dmin = SELECT(dmin, fmin(dmin, d), u);
                dmax = SELECT(dmax, fmax(dmax, d), u);
            }
            VSTORE(f, 0, F + k * VW);
            prev = x;
            usable_prev = usable;
        }
        anysat |= sat;
        if (jump_thr > 0.0) {
            /* find_jump's first test for all lanes at once: the lanes it does not settle are searched */
            vlong search = MASK(nv >= JUMP_MIN_DIFFS)
                & MASK(fmax(dmax - dmin, dmax - dmin) > jump_thr * sqrt(2.0 * sg2 + (fmax(dmin, 0.0) / tau) * pois_diag));
#if NDIFF >= JUMP_MIN_DIFFS && NDIFF <= SORT_MAX
            if (ANY(search & allused))
                search &= ~no_jump_sorted(D, dmin, dmax, sg2, tau, pois_diag, jump_thr, allused);
#endif
            if (ANY(search)) {
                long wanted[VW];
                int found[VW];
                VSTORE(search, 0, wanted);
                for (int l = 0; l < VW; ++l)
                    found[l] = wanted[l] ? lane_jumps(D, U, F, l, sg2, tau, pois_diag, jump_thr, Dl, usedl, A) : 0;
                const vint more = VLOAD(0, found);
                njump += more;
                allused &= MASK(more == 0);
            }
        }
        if (!ANY(~allused)) {
            /* every lane uses every difference: one run of NDIFF, the same sums without the masks */
            vdouble s1 = ZERO, s2 = ZERO;
            for (int j = 0; j < NDIFF; ++j) {
                const vdouble dj = VLOAD(0, D + j * VW);
                const double pd = (double)(j + 1);
                s1 = s1 + pd * dj;
                s2 = s2 + pd * pd * dj;
            }
            const double L = (double)NDIFF, L3 = L * (L + 1.0) * (L + 2.0);
            P = P + ((L + 1.0) * s1 - s2);
            S = S + L3 / 6.0;
            W2 = W2 + L3 * (L * L + 2.0 * L + 2.0) / 30.0;
            Q = Q + L3 / 3.0;
        } else {
        vdouble s1 = ZERO, s2 = ZERO, pos = ZERO;
        for (int j = 0; j < NDIFF; ++j) {
            const vlong u = VLOAD(0, U + j * VW);
            const vdouble dj = VLOAD(0, D + j * VW);
            const vdouble pd = pos + 1.0;
            pos = SELECT(pos, pd, u);
            s1 = SELECT(s1, s1 + pd * dj, u);
            s2 = SELECT(s2, s2 + pd * pd * dj, u);
            const vlong end = j == NDIFF - 1 ? u : u & ~VLOAD(0, U + (j + 1) * VW);
            const vdouble L = pos, L3 = L * (L + 1.0) * (L + 2.0);
            P = SELECT(P, P + ((L + 1.0) * s1 - s2), end);
            S = SELECT(S, S + L3 / 6.0, end);
            W2 = SELECT(W2, W2 + L3 * (L * L + 2.0 * L + 2.0) / 30.0, end);
            Q = SELECT(Q, Q + L3 / 3.0, end);
            s1 = SELECT(s1, ZERO, end);
            s2 = SELECT(s2, ZERO, end);
            pos = SELECT(pos, ZERO, end);
        }
        }
#if WANT_GDQ
        for (int k = 0; k < NGROUPS; ++k)
            store_uchar(VLOAD(0, F + k * VW), gdq_out + base + (size_t)k * npix, nvalid);
#endif
#if WEIGHTING == 0
        if (nints > 1) {
            for (int w = 0; w < NWORDS; ++w) {
                vulong word = 0;
                for (int j = 64 * w; j < NDIFF && j < 64 * (w + 1); ++j)
                    word |= (CONVERT_V(ulong, VLOAD(0, U + j * VW)) & (ulong)1) << (ulong)(j - 64 * w);
                store_ulong(word, bits + ((size_t)i * NWORDS + w) * npix + p, nvalid);
            }
        }
#endif
    }
    const vdouble lam0 = SELECT(ZERO, fmax(P / (tau * S), 0.0), MASK(S > 0.0));
    WW = W2 - 0.5 * Q;

#if WEIGHTING == 0
    /* pass 2: GLS weights w = T'^-1 1 per run, T' = T / a = tridiag(r, 1, r), r = b / a, through the
     * leading minors M_0 = M_1 = 1, M_{q+1} = M_q - r^2 M_{q-1} and e_q = M_q - r e_{q-1} (Thomas
     * without a division in the recurrences): w_q = (e_q - r M_q w_{q+1}) / M_{q+1}.  The common
     * factor 1/a of w cancels in the rate and the variance.  Sums in reverse order. */
    const vdouble a = 2.0 * sg2 + lam0 * pois_diag;
    const vlong apos = MASK(a > 0.0);
    const vdouble r = SELECT(ZERO, (lam0 * ccorr - sg2) / a, apos);
    const vdouble r2 = r * r;
    P = ZERO;
    S = ZERO;
    W2 = ZERO;
    WW = ZERO;
    Q = ZERO;
    for (uint i = 0; i < nints; ++i) {
        if (nints > 1)
            reload(sci, bits, (size_t)i * NGROUPS * npix + p, (size_t)i * NWORDS * npix + p, npix, nvalid, inv_gain, D, U);
        vdouble mq = ONE, mq1 = ONE, e = ZERO;         /* M_q, M_{q+1}, e_{q-1} of the run */
        vlong allused = -1;
        for (int j = 0; j < NDIFF; ++j)
            allused &= VLOAD(0, U + j * VW);
        if (!ANY(~allused)) {                          /* one run in every lane: no masks */
            for (int j = 0; j < NDIFF; ++j) {
                e = mq - r * e;
                VSTORE(e, 0, B + j * VW);
                VSTORE(r * mq, 0, C + j * VW);
                VSTORE(1.0 / mq1, 0, A + j * VW);
                const vdouble next = mq1 - r2 * mq;
                mq = mq1;
                mq1 = next;
            }
        } else
        for (int j = 0; j < NDIFF; ++j) {
            const vlong u = VLOAD(0, U + j * VW);
            const vdouble en = mq - r * e;
            VSTORE(en, 0, B + j * VW);
            VSTORE(r * mq, 0, C + j * VW);
            VSTORE(1.0 / mq1, 0, A + j * VW);
            const vdouble next = mq1 - r2 * mq;
            e = SELECT(ZERO, en, u);
            mq = SELECT(ONE, mq1, u);
            mq1 = SELECT(ONE, next, u);
        }
        vdouble wnext = ZERO;
        for (int j = NDIFF - 1; j >= 0; --j) {
            const vdouble wg = (VLOAD(0, B + j * VW) - VLOAD(0, C + j * VW) * wnext) * VLOAD(0, A + j * VW);
            const vdouble w = SELECT(ZERO, SELECT(ONE, wg, apos), VLOAD(0, U + j * VW));
            P = P + w * VLOAD(0, D + j * VW);
            S = S + w;
            W2 = W2 + w * w;
            WW = WW + w * wnext;
            const vdouble step = w - wnext;
            Q = Q + step * step;
            wnext = w;
        }
        Q = Q + wnext * wnext;
    }
#endif

    const vlong ok = MASK(S > 0.0);
    const vdouble norm = tau * S;
    const vdouble n2 = norm * norm;
    const vdouble var_read = sg2 * Q / n2;
    const vdouble var_pois = lam0 * (pois_diag * W2 + 2.0 * ccorr * WW) / n2;
    const vdouble nan = (vdouble)(NAN);
    store_double(SELECT(nan, P / norm, ok), rate_out + p, nvalid);
    store_double(SELECT(nan, var_read + var_pois, ok), var_out + p, nvalid);
    store_double(SELECT(nan, var_pois, ok), vpois_out + p, nvalid);
    store_double(SELECT(nan, var_read, ok), vread_out + p, nvalid);
    const vuint dq = load_uint(pixeldq + p, nvalid) | (CONVERT_V(uint, anysat) & (uint)DQ_SAT)
        | (CONVERT_V(uint, MASK(njump != 0)) & (uint)DQ_JUMP) | (CONVERT_V(uint, ~ok) & (uint)DQ_DNU);
    store_uint(dq, dq_out + p, nvalid);
    store_int(njump, njump_out + p, nvalid);
}
