/*
 * Mixed-radix (2, 3, 4, 5) Stockham autosort FFT passes, complex real.
 *
 * One pass of radix R on a transform of length N, with p = product of the
 * radices of the previous passes (p = 1 for the first pass), T = N / R
 * butterflies per transform.  Butterfly i (0 <= i < T), k = i mod p:
 *
 *     u_r = src[i + r T] * w^(r k N / (p R)),       r = 0 .. R-1
 *     U_q = sum_r u_r exp(s 2 pi i r q / R)           (radix-R DFT)
 *     dst[(i - k) R + k + q p] = U_q
 *
 * with w = exp(s 2 pi i / N), s = -1 forward, +1 inverse (unnormalised).
 * After the last pass (p R = N) dst holds the DFT in natural order.
 * tw[m] = (cos 2 pi m / N, sin 2 pi m / N), m < N, computed on the host in
 * float64; the pass uses (tw.x, s tw.y).  twstep = N / (p R).
 *
 * Transforms run along the middle axis of a batch of arrays (B, N, M), element
 * (b, n, c) at (b N + n) M + c: fft_pass_R has NDRange (M, N / R, B), so
 * neighbouring work items touch neighbouring columns c (contiguous loads and
 * stores: vectorises on CPUs, coalesces on GPUs) with uniform twiddles.  The
 * other axis of a 2-D transform is reached by transposing (B, N, M) -> (B, M, N)
 * with `transpose` (CPUs) or `transpose_tiled` (16 x 16 tiles in local memory,
 * GPUs): on PoCL a transpose plus contiguous passes is faster than passes along
 * the contiguous axis.
 */

#include "vector_types.cl"

#define CMUL(a, b) ((real2)((a).x * (b).x - (a).y * (b).y, (a).x * (b).y + (a).y * (b).x))
/* multiply by s*i: (x + iy)(s i) = -s y + i s x */
#define MUL_SI(a, s) ((real2)(-(s) * (a).y, (s) * (a).x))

#define SQRT3_2 0.86602540378443864676
#define C5_1 0.30901699437494742410   /* cos(2 pi / 5) */
#define C5_2 -0.80901699437494742410  /* cos(4 pi / 5) */
#define S5_1 0.95105651629515357212   /* sin(2 pi / 5) */
#define S5_2 0.58778525229247312917   /* sin(4 pi / 5) */

#define BUTTERFLY_2(u, s)                                                   \
    {                                                                       \
        const real2 a = u[0], b = u[1];                                   \
        u[0] = a + b;                                                       \
        u[1] = a - b;                                                       \
    }

#define BUTTERFLY_3(u, s)                                                   \
    {                                                                       \
        const real2 t = u[1] + u[2];                                      \
        const real2 d = MUL_SI(u[1] - u[2], (s) * SQRT3_2);               \
        const real2 m = u[0] - 0.5 * t;                                   \
        u[0] = u[0] + t;                                                    \
        u[1] = m + d;                                                       \
        u[2] = m - d;                                                       \
    }

#define BUTTERFLY_4(u, s)                                                   \
    {                                                                       \
        const real2 a = u[0] + u[2], b = u[0] - u[2];                     \
        const real2 c = u[1] + u[3], d = MUL_SI(u[1] - u[3], s);          \
        u[0] = a + c;                                                       \
        u[2] = a - c;                                                       \
        u[1] = b + d;                                                       \
        u[3] = b - d;                                                       \
    }

#define BUTTERFLY_5(u, s)                                                   \
    {                                                                       \
        const real2 t1 = u[1] + u[4], t2 = u[2] + u[3];                   \
        const real2 d1 = u[1] - u[4], d2 = u[2] - u[3];                   \
        const real2 a1 = u[0] + C5_1 * t1 + C5_2 * t2;                    \
        const real2 a2 = u[0] + C5_2 * t1 + C5_1 * t2;                    \
        const real2 b1 = MUL_SI(S5_1 * d1 + S5_2 * d2, s);                \
        const real2 b2 = MUL_SI(S5_2 * d1 - S5_1 * d2, s);                \
        u[0] = u[0] + t1 + t2;                                              \
        u[1] = a1 + b1;                                                     \
        u[4] = a1 - b1;                                                     \
        u[2] = a2 + b2;                                                     \
        u[3] = a2 - b2;                                                     \
    }

#define DEFINE_PASS(R)                                                      \
__kernel void fft_pass_##R(__global const real2 *restrict src,            \
                           __global real2 *restrict dst,                  \
                           __global const real2 *restrict tw,             \
                           const int N, const int p, const int twstep,      \
                           const real s, const int M)                     \
{                                                                           \
    const int i = get_global_id(1);                                         \
    const size_t base = (size_t)get_global_id(2) * (size_t)N * (size_t)M    \
                        + (size_t)get_global_id(0);                         \
    const size_t es = (size_t)M;                                            \
    const int T = N / R;                                                    \
    const int k = i % p;                                                    \
    real2 u[R];                                                           \
    _Pragma("unroll")                                                       \
    for (int r = 0; r < R; ++r)                                             \
        u[r] = src[base + (size_t)(i + r * T) * es];                        \
    _Pragma("unroll")                                                       \
    for (int r = 1; r < R; ++r) {                                           \
        real2 w = tw[r * k * twstep];                                     \
        w.y *= s;                                                           \
        u[r] = CMUL(u[r], w);                                               \
    }                                                                       \
    BUTTERFLY_##R(u, s)                                                     \
    const int j = (i - k) * R + k;                                          \
    _Pragma("unroll")                                                       \
    for (int r = 0; r < R; ++r)                                             \
        dst[base + (size_t)(j + r * p) * es] = u[r];                        \
}

DEFINE_PASS(2)
DEFINE_PASS(3)
DEFINE_PASS(4)
DEFINE_PASS(5)

/* (B, N, M) -> (B, M, N); NDRange (M, N, B) */
__kernel void transpose(__global const real2 *restrict src, __global real2 *restrict dst,
                        const int N, const int M)
{
    const int c = get_global_id(0), n = get_global_id(1), b = get_global_id(2);
    dst[((size_t)b * M + c) * N + n] = src[((size_t)b * N + n) * M + c];
}

/* same, 16 x 16 tiles through local memory; NDRange (ceil16(M), ceil16(N), B), local (16, 16, 1) */
#define TT 16
__kernel __attribute__((reqd_work_group_size(TT, TT, 1)))
void transpose_tiled(__global const real2 *restrict src, __global real2 *restrict dst,
                     const int N, const int M)
{
    __local real2 tile[TT][TT + 1];
    const int lx = get_local_id(0), ly = get_local_id(1), b = get_global_id(2);
    const int c = get_group_id(0) * TT + lx, n = get_group_id(1) * TT + ly;
    if (c < M && n < N)
        tile[ly][lx] = src[((size_t)b * N + n) * M + c];
    barrier(CLK_LOCAL_MEM_FENCE);
    const int n2 = get_group_id(1) * TT + lx, c2 = get_group_id(0) * TT + ly;
    if (n2 < N && c2 < M)
        dst[((size_t)b * M + c2) * N + n2] = tile[lx][ly];
}
