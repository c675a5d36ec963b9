/*
 * ramp_fit.cl: up-the-ramp fit of MACC group means, one work item per pixel, all integrations.
 *
 * Input (flat block of npix pixels, group-major): sci (nints, NGROUPS, npix) [DN] as ushort (raw
 * ADU) or double (corrected DN, -DSCI_DOUBLE=1), GROUPDQ (same shape, JWST bits), PIXELDQ (npix).
 * With D_j = (g_{j+1} - g_j) / gain [e-] the differences of consecutive group means:
 *
 * 1. saturation: a group flagged SATURATED or reading >= satlim, and every later group, is
 *    SATURATED; a group is usable unless SATURATED or DO_NOT_USE; difference j is used when
 *    groups j and j+1 are usable and group j+1 carries no JUMP_DET flag;
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
 * (GLS, nints > 1).  Build with -DNGROUPS=n -DWEIGHTING=0|1 -DSCI_DOUBLE=0|1 -DWANT_GDQ=0|1.
 * NumPy twin: slicersim/backends/ramp_fit.py (fit_block_numpy), same operation order.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

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
typedef double sci_t;
#else
typedef ushort sci_t;
#endif

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

/* D [e-] of integration `base` and its used flags from the bits of pass 1 */
inline void reload(__global const sci_t *sci, __global const ulong *bits, const size_t base, const size_t bbase,
                   const uint npix, const double inv_gain, double *D, uchar *used)
{
    double prev = (double)sci[base];
    for (int k = 1; k < NGROUPS; ++k) {
        const double x = (double)sci[base + (size_t)k * npix];
        D[k - 1] = (x - prev) * inv_gain;
        prev = x;
    }
    for (int w = 0; w < NWORDS; ++w) {
        const ulong word = bits[bbase + (size_t)w * npix];
        for (int j = 64 * w; j < NDIFF && j < 64 * (w + 1); ++j)
            used[j] = (word >> (j - 64 * w)) & 1ul;
    }
}

__kernel void ramp_fit(__global const sci_t *sci, __global const uchar *gdq_in, __global uchar *gdq_out,
                       __global ulong *bits, __global const uint *pixeldq, __global double *rate_out,
                       __global double *var_out, __global double *vpois_out, __global double *vread_out,
                       __global uint *dq_out, __global int *njump_out, const uint npix, const uint nints,
                       const double inv_gain, const double sg2, const double tau, const double ccorr,
                       const double satlim, const double jump_thr)
{
    const size_t p = get_global_id(0);
    if (p >= npix)
        return;
    double D[NDIFF], A[NDIFF], B[NDIFF], C[NDIFF];
    uchar used[NDIFF], F[NGROUPS];
    const double pois_diag = tau - 2.0 * ccorr;     /* Poisson variance of a difference per e-/s [s] */
    int njump = 0;
    uint anysat = 0;
    double P = 0.0, S = 0.0, W2 = 0.0, Q = 0.0, WW;

    /* pass 1: saturation, jumps, OLS sums (closed forms per run of L differences) */
    for (uint i = 0; i < nints; ++i) {
        const size_t base = (size_t)i * NGROUPS * npix + p;
        uint sat = 0;
        uchar usable_prev = 0;
        double prev = 0.0, dmin = INFINITY, dmax = -INFINITY;
        int nv = 0;
        for (int k = 0; k < NGROUPS; ++k) {
            const size_t at = base + (size_t)k * npix;
            uchar f = gdq_in[at];
            const double x = (double)sci[at];
            if ((f & DQ_SAT) || x >= satlim)
                sat = 1;
            if (sat)
                f |= DQ_SAT;
            const uchar usable = !(f & (DQ_SAT | DQ_DNU));
            if (k > 0) {
                const double d = (x - prev) * inv_gain;
                const uchar both = usable_prev && usable;
                if (both && (f & DQ_JUMP))
                    ++njump;
                const uchar u = both && !(f & DQ_JUMP);
                D[k - 1] = d;
                used[k - 1] = u;
                if (u) {
                    ++nv;
                    dmin = fmin(dmin, d);
                    dmax = fmax(dmax, d);
                }
            }
            F[k] = f;
            prev = x;
            usable_prev = usable;
        }
        anysat |= sat;
        double med;
        while (jump_thr > 0.0 && nv >= JUMP_MIN_DIFFS
               && find_jump(D, used, nv, dmin, dmax, sg2, tau, pois_diag, jump_thr, A, &med)) {
            int jbest = -1;
            double dbest = -1.0;
            for (int j = 0; j < NDIFF; ++j) {
                const double dev = used[j] ? fabs(D[j] - med) : -1.0;
                if (dev > dbest) {
                    dbest = dev;
                    jbest = j;
                }
            }
            used[jbest] = 0;
            F[jbest + 1] |= DQ_JUMP;
            ++njump;
            nv = 0;
            dmin = INFINITY;
            dmax = -INFINITY;
            for (int j = 0; j < NDIFF; ++j) {
                if (used[j]) {
                    ++nv;
                    dmin = fmin(dmin, D[j]);
                    dmax = fmax(dmax, D[j]);
                }
            }
        }
        double s1 = 0.0, s2 = 0.0;
        int pos = 0;
        for (int j = 0; j < NDIFF; ++j) {
            if (!used[j])
                continue;
            ++pos;
            const double pd = (double)pos;
            s1 += pd * D[j];
            s2 += pd * pd * D[j];
            if (j == NDIFF - 1 || !used[j + 1]) {
                const double L = pd, L3 = L * (L + 1.0) * (L + 2.0);
                P += (L + 1.0) * s1 - s2;
                S += L3 / 6.0;
                W2 += L3 * (L * L + 2.0 * L + 2.0) / 30.0;
                Q += L3 / 3.0;
                s1 = 0.0;
                s2 = 0.0;
                pos = 0;
            }
        }
#if WANT_GDQ
        for (int k = 0; k < NGROUPS; ++k)
            gdq_out[base + (size_t)k * npix] = F[k];
#endif
#if WEIGHTING == 0
        if (nints > 1) {
            for (int w = 0; w < NWORDS; ++w) {
                ulong word = 0;
                for (int j = 64 * w; j < NDIFF && j < 64 * (w + 1); ++j)
                    word |= (ulong)used[j] << (j - 64 * w);
                bits[((size_t)i * NWORDS + w) * npix + p] = word;
            }
        }
#endif
    }
    const double lam0 = S > 0.0 ? fmax(P / (tau * S), 0.0) : 0.0;
    WW = W2 - 0.5 * Q;

#if WEIGHTING == 0
    /* pass 2: GLS weights w = T'^-1 1 per run, T' = T / a = tridiag(r, 1, r), r = b / a, through the
     * leading minors M_0 = M_1 = 1, M_{q+1} = M_q - r^2 M_{q-1} and e_q = M_q - r e_{q-1} (Thomas
     * without a division in the recurrences): w_q = (e_q - r M_q w_{q+1}) / M_{q+1}.  The common
     * factor 1/a of w cancels in the rate and the variance.  Sums in reverse order. */
    const double a = 2.0 * sg2 + lam0 * pois_diag;
    const double r = a > 0.0 ? (lam0 * ccorr - sg2) / a : 0.0;
    const double r2 = r * r;
    P = 0.0;
    S = 0.0;
    W2 = 0.0;
    WW = 0.0;
    Q = 0.0;
    for (uint i = 0; i < nints; ++i) {
        if (nints > 1)
            reload(sci, bits, (size_t)i * NGROUPS * npix + p, (size_t)i * NWORDS * npix + p, npix, inv_gain, D, used);
        double mq = 1.0, mq1 = 1.0, e = 0.0;           /* M_q, M_{q+1}, e_{q-1} of the run */
        for (int j = 0; j < NDIFF; ++j) {
            if (used[j]) {
                e = mq - r * e;
                B[j] = e;
                C[j] = r * mq;
                A[j] = 1.0 / mq1;
                const double next = mq1 - r2 * mq;
                mq = mq1;
                mq1 = next;
            } else {
                mq = 1.0;
                mq1 = 1.0;
                e = 0.0;
            }
        }
        double wnext = 0.0;
        for (int j = NDIFF - 1; j >= 0; --j) {
            const double w = used[j] ? (a > 0.0 ? (B[j] - C[j] * wnext) * A[j] : 1.0) : 0.0;
            P += w * D[j];
            S += w;
            W2 += w * w;
            WW += w * wnext;
            const double step = w - wnext;
            Q += step * step;
            wnext = w;
        }
        Q += wnext * wnext;
    }
#endif

    uint dq = pixeldq[p] | (anysat ? DQ_SAT : 0u) | (njump ? DQ_JUMP : 0u);
    if (S > 0.0) {
        const double norm = tau * S;
        const double n2 = norm * norm;
        const double var_read = sg2 * Q / n2;
        const double var_pois = lam0 * (pois_diag * W2 + 2.0 * ccorr * WW) / n2;
        rate_out[p] = P / norm;
        var_out[p] = var_read + var_pois;
        vpois_out[p] = var_pois;
        vread_out[p] = var_read;
    } else {
        dq |= DQ_DNU;
        rate_out[p] = NAN;
        var_out[p] = NAN;
        vpois_out[p] = NAN;
        vread_out[p] = NAN;
    }
    dq_out[p] = dq;
    njump_out[p] = njump;
}
