/* knn_radius.cl -- the squared distance of every point to its K-th nearest point (the point
 * itself the first), on the grid of a DeviceCloud: the k-NN radius (clcurv/ops/knn_radius.py).
 *
 * One work-item per sorted point; the same fixed-order walk over the 27 cells as the
 * operators (neighbors.h), the candidates within the reach the host passes (open ball
 * d^2 < cball.x: the cloud's cell c squared, or less, FIRST_REACH c for a tight cloud's
 * first walk, clcurv/ops/knn_radius.py), or with extend within the point's reach (reach2: up
 * to 1.5 c, the largest ball inside its 27 cells). One walk, vector operations only,
 * keeps lane by lane the KNN_LEVELS smallest d^2 of the lane (chunks merged KNN_BATCH at a
 * time by a min/max network over the KNN_LEVELS vectors, KNN_MERGE) and the lane's count.
 * The K-th smallest is then selected from the kept values by two packed histograms (bins of d^2,
 * then sub-bins of the bin that holds the K-th: one vector add per kept vector each, the
 * counts of a lane packed in the nibbles of a uint) and a vector minimum within the
 * sub-bin. Every value below m, the smallest of the largest kept values of the lanes that
 * held more than KNN_LEVELS candidates (and dropped the rest), is kept, so a value found at
 * most m is exact (its ties counted at least once). Otherwise (a lane held more than
 * KNN_LEVELS of the K nearest: dense spots, many duplicates; ~0.5% of the points at K = 30
 * on the first cell of a uniform sphere, where the test by bins of before sent ~2%) the
 * point takes the counting path instead, which narrows an interval of d^2 by
 * counting walks until it holds at most KNN_CAP candidates, gathers them and picks the
 * rank (an interval that cannot be narrowed, many equal distances, gives its upper end).
 * (A walk gathering every candidate lane by lane into a buffer cost ~5x this one on PoCL:
 * scalar lane loops. The selection by rounds of vector minima within 8 bins of the
 * kept values, before the histograms, cost as much as the walk.)
 * Points whose prev[g] is finite (found at a smaller cell, sorted order of this cloud) are
 * copied, not walked again.
 * Output d2k[g] (sorted order): the K-th smallest d^2, or +INFINITY when fewer than K
 * points lie within the walk's reach (reach2: the host's, at most c, or with extend up to
 * 1.5 c; the host then walks the cell or bins at a larger one). ball_r2 turns the last
 * binning's d2k into the operators' per-point r^2.
 * Build options: KNN_K (1 .. clcurv.ops.knn_radius.MAX_K); KNN_LEVELS (1 .. 15) the levels kept
 * per lane (clcurv/ops/knn_radius.py:knn_levels; tests: 1 sends nearly every point down the
 * counting path).
 */
#include "common.h"
#include "neighbors.h"

#if !defined(KNN_K) || KNN_K < 1
#error "knn_radius.cl needs KNN_K (clcurv/ops/knn_radius.py)"
#endif

/* KNN_LEVELS, the smallest d^2 kept per lane (4 to 15 vectors: a lane's count per bin fits
 * a nibble, packed_prefix), is the host's choice (clcurv/ops/knn_radius.py:knn_levels): enough
 * that few points have a lane holding more of their K nearest than it keeps, since those
 * take the counting path. At K = 30 on the first cell of a 1M uniform sphere: VW = 8,
 * kernel 102 ms with 8 levels, 107 with 10, 125 with 7, 191 with 6; VW = 16 (AVX-512),
 * 144 ms with 4, ~92 with 5, ~83 with 6, ~87 with 7, ~92 with 8 (the same values). */
#ifndef KNN_LEVELS
#error "knn_radius.cl needs KNN_LEVELS (clcurv/ops/knn_radius.py:knn_levels)"
#endif
#if KNN_LEVELS < 1 || KNN_LEVELS > 15
#error "KNN_LEVELS must be 1 .. 15"
#endif

/* KNN_BATCH (>= 1) chunks of candidates are merged into the kept values at once by
 * KNN_MERGE, the host's comparator network (clcurv/ops/knn_radius.py:merge_network): the batch
 * sorted, then an odd-even merge pruned to the KNN_LEVELS smallest, which it leaves
 * sorted. The same values kept as inserting each chunk alone (the KNN_LEVELS smallest of
 * each lane), in fewer operations: 24 min/max per 2 chunks at 8 levels against 30. */
#if !defined(KNN_BATCH) || KNN_BATCH < 1 || !defined(KNN_MERGE)
#error "knn_radius.cl needs KNN_BATCH and KNN_MERGE (clcurv/ops/knn_radius.py:program_defines)"
#endif
#define KNN_CE(x, y) { const IREALV lo_ = min(x, y); y = max(x, y); x = lo_; }
#define KNN_LO(x, y) x = min(x, y);
#define KNN_HI(x, y) y = max(x, y);

#define KNN_CAP 64          /* the counting path gathers at most this many candidates */

#define NBIN 8              /* bins per counting pass */
#define KNN_ROUNDS 12       /* counting passes at most (each narrows the interval 8x) */

/* d^2 of the chunk's lanes (chunk_offsets_d2's) and the mask of those in the open ball. */
inline IREALV chunk_d2(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                       uint i, uint end, REAL3 pr, REAL2 ball, REALV *d2)
{
    REALV dx, dy, dz;
    return chunk_offsets_d2(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz, d2);
}

/* Append the lanes of d2 set in m to buf (got values so far). Every lane is written, at
 * the next free slot (a live lane then keeps it), so buf has a scratch slot past KNN_CAP
 * values: with KNN_CAP values held, the lanes that follow write there, not over the last
 * value (past KNN_CAP the count goes on: the caller checks got <= KNN_CAP). */
inline uint append_lanes(REALV d2, IREALV m, REAL *buf, uint got)
{
    REAL dl[VW];
    IREAL ml[VW];
    CAT(vstore, VW)(d2, 0, dl);
    CAT(vstore, VW)(m, 0, ml);
    for (int l = 0; l < VW; ++l) {
        buf[min(got, (uint)KNN_CAP)] = dl[l];
        got += ml[l] ? 1 : 0;
    }
    return got;
}

/* The rank-th smallest (from 0) of buf[0 .. cnt) (Hoare's selection; reorders buf). */
inline REAL select_rank(REAL *buf, uint cnt, uint rank)
{
    int lo = 0, hi = (int)cnt - 1;
    const int k = (int)rank;
    while (lo < hi) {
        const REAL pivot = buf[(lo + hi) / 2];
        int i = lo, j = hi;
        while (i <= j) {
            while (buf[i] < pivot) ++i;
            while (buf[j] > pivot) --j;
            if (i <= j) {
                const REAL t = buf[i];
                buf[i] = buf[j];
                buf[j] = t;
                ++i;
                --j;
            }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else break;
    }
    return buf[k];
}

/* The counting path (see the top) for a point whose ball holds more than KNN_CAP
 * candidates: the K-th smallest d^2, buf (KNN_CAP + 1 values) as scratch. */
inline REAL kth_by_counting(__global const REAL *XA, __global const REAL *Y,
                            __global const REAL *Z, __global const uint2 *ranges, uint cell,
                            REAL3 p, REAL2 ball, REAL *buf)
{
    REAL lo = 0, hi = ball.x;               /* the K-th d^2 lies in [lo, hi) */
    uint need = KNN_K;                      /* its rank within [lo, hi), from 1 */
    uint inside = 0;                        /* candidates in [lo, hi) */
    for (int round = 0; round < KNN_ROUNDS; ++round) {
        REAL edge[NBIN];
        for (int b = 0; b < NBIN - 1; ++b) edge[b] = lo + (hi - lo) * (REAL)(b + 1) / NBIN;
        edge[NBIN - 1] = hi;
        REALV cnt[NBIN];
        for (int b = 0; b < NBIN; ++b) cnt[b] = 0;
        NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
            REALV d2;
            const IREALV m = chunk_d2(XA, Y, Z, i, end, pr, ball, &d2) & isgreaterequal(d2, (REALV)lo);
            for (int b = 0; b < NBIN; ++b)
                cnt[b] += select((REALV)0, (REALV)1, m & isless(d2, (REALV)edge[b]));
        NEIGHBOR_CHUNKS_END
        uint below = 0, b = 0;
        for (; b < NBIN; ++b) {
            const uint c = (uint)hsum(cnt[b]);
            if (c >= need) { inside = c - below; break; }
            below = c;
        }
        if (b == NBIN) return (REAL)INFINITY;               /* fewer than K within c */
        const REAL nlo = b ? edge[b - 1] : lo, nhi = edge[b];
        need -= below;
        if (inside <= KNN_CAP || !(nlo < nhi)) { lo = nlo; hi = nhi; break; }
        if (nlo == lo && nhi == hi) break;                   /* cannot narrow: ties */
        lo = nlo; hi = nhi;
    }
    if (inside > KNN_CAP) return hi;                         /* equal distances: its end */
    /* gather the candidates of [lo, hi) and pick the need-th smallest */
    uint got = 0;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        REALV d2;
        const IREALV m = chunk_d2(XA, Y, Z, i, end, pr, ball, &d2)
                         & isgreaterequal(d2, (REALV)lo) & isless(d2, (REALV)hi);
        if (any_lane(m)) got = append_lanes(d2, m, buf, got);
    NEIGHBOR_CHUNKS_END
    return select_rank(buf, got, need - 1);
}

/* d^2 >= 0 as integer bits: ordered as the values (+INFINITY last), and integer min/max are
 * single vector instructions (float fmin/fmax and compare-select cost ~2x) */
#define AS_IREALV CAT(as_, IREALV)
#define AS_IREAL CAT(as_, IREAL)
#define AS_REAL CAT(as_, REAL)
#define INF_BITS AS_IREAL((REAL)INFINITY)

/* The smallest lane of v */
LANE_REDUCTION(min_lane, IREAL, min)


/* How many lanes of a mask are set */
inline uint count_lanes(IREALV m)
{
    return (uint)(-hsum(CAT(convert_, REALV)(m)));
}

#define PB 7            /* bins per packed histogram (field PB: the values outside them) */
#define UINTV CAT(uint, VW)
#define CONVERT_UINTV CAT(convert_uint, VW)
#define AS_REALV CAT(as_, REALV)
#define MASK_IREALV CAT(convert_, IREALV)    /* an int comparison mask as an IREALV mask */

/* Sum of the lanes of a uint vector */
LANE_REDUCTION(hsum_uint, uint, LANE_ADD)


/* The cumulative histogram of the fields f[t] (0 .. PB) of the kept values: byte b of the
 * result = the number of values whose field is <= b. A lane counts its fields in the 8
 * nibbles of a uint (at most KNN_LEVELS <= 15 values per lane); the lanes are summed as
 * bytes (fields 0 2 4 6 and 1 3 5 7 apart: at most 15 VW <= 240 per byte), whose bytes are
 * spread to every other byte of a ulong and interleaved (shifts and masks: 14 operations,
 * against 32 for a loop over the bytes), whose product by 0x0101..01 adds each byte to
 * those above it. */
inline ulong packed_prefix(const UINTV f[KNN_LEVELS])
{
    UINTV h = 0;
    for (int t = 0; t < KNN_LEVELS; ++t)
        h += (UINTV)1 << (f[t] << 2);
    ulong e = hsum_uint(h & (UINTV)0x0F0F0F0Fu);              /* fields 0 2 4 6 */
    ulong o = hsum_uint((h >> 4) & (UINTV)0x0F0F0F0Fu);       /* fields 1 3 5 7 */
    e = (e | e << 16) & 0x0000FFFF0000FFFFUL;                  /* byte i to byte 2 i */
    e = (e | e << 8) & 0x00FF00FF00FF00FFUL;
    o = (o | o << 16) & 0x0000FFFF0000FFFFUL;
    o = (o | o << 8) & 0x00FF00FF00FF00FFUL;
    return (e | o << 8) * 0x0101010101010101UL;
}

/* The first field b < PB whose cumulative count (packed_prefix) reaches need (PB: none),
 * and the count of the fields before it in *below. With every count and need below 128
 * (KNN_LEVELS VW <= 127, KNN_K <= 128: need only decreases), the PB fields are compared
 * at once: (byte | 0x80) - need keeps bit 7 exactly where byte >= need, no borrow crossing
 * a byte, and the fields below need are PB minus their popcount; otherwise one compare
 * per field. (The byte loop cost ~5 ms of the 1M-sphere walk's ~100.) */
#define FIELD_HIGH (((1UL << (8 * PB)) - 1) & 0x8080808080808080UL)
inline uint first_field(ulong prefix, uint need, uint *below)
{
#if KNN_LEVELS * VW <= 127 && KNN_K <= 128
    const ulong ge = ((prefix | FIELD_HIGH) - (ulong)need * (FIELD_HIGH >> 7)) & FIELD_HIGH;
    const uint b = PB - (uint)popcount(ge);
#else
    uint b = 0;
    for (int i = 0; i < PB; ++i) b += ((prefix >> (8 * i)) & 0xff) < need;
#endif
    *below = (uint)(((prefix << 8) >> (8 * min(b, (uint)(PB - 1)))) & 0xff);
    return b;
}

/* The need-th smallest (from 1) of the kept values a[] (bits, ascending per lane), or NAN
 * when the kept values cannot tell (the counting path's case, see the top). Bins of d^2:
 * field trunc(d^2 s) (0 .. PB - 1 for d^2 < c^2, s = (PB - 1/2) / c^2; empty slots,
 * INF, in field PB); then the bin b that holds the need-th, split into sub-bins
 * trunc(d^2 s PB) - PB b (clamped: monotone in d^2, which is all the counts need); then
 * the need'-th smallest of that sub-bin by rounds of vector minima (usually one). */
inline REAL kth_of_levels(IREALV a[KNN_LEVELS], IREALV lanes, REAL c2, uint need)
{
    const REAL s = ((REAL)PB - (REAL)0.5) / c2, s2 = s * (REAL)PB;
    if (!(s2 < (REAL)INFINITY)) return (REAL)NAN;             /* a cell below ~1e-19 */
    /* every value below m, the smallest of the largest kept values of the lanes that
       dropped some (INF: none dropped), is kept */
    const IREAL m = min_lane(select((IREALV)INF_BITS, a[KNN_LEVELS - 1],
                                    lanes < (IREALV)(-KNN_LEVELS)));
    UINTV f[KNN_LEVELS];
    for (int t = 0; t < KNN_LEVELS; ++t)
        f[t] = CONVERT_UINTV(fmin(AS_REALV(a[t]) * s, (REALV)PB));
    uint below;
    const uint b = first_field(packed_prefix(f), need, &below);
    if (b == PB) return (REAL)NAN;        /* fewer kept values than need: lanes dropped some */
    need -= below;
    const UINTV lo = (UINTV)(PB * b);
    for (int t = 0; t < KNN_LEVELS; ++t) {
        const UINTV u = CONVERT_UINTV(fmin(AS_REALV(a[t]) * s2, (REALV)(PB * PB + PB)));
        f[t] = select((UINTV)PB, min(max(u, lo) - lo, (UINTV)(PB - 1)), f[t] == (UINTV)b);
    }
    const uint b2 = first_field(packed_prefix(f), need, &below);
    need -= below;
    for (int t = 0; t < KNN_LEVELS; ++t)
        a[t] = select((IREALV)INF_BITS, a[t], MASK_IREALV(f[t] == (UINTV)b2));
    IREAL x = INF_BITS;
    for (int round = 0; round < KNN_LEVELS * VW; ++round) {    /* ends at need <= c */
        IREALV mn = a[0];
        for (int t = 1; t < KNN_LEVELS; ++t) mn = min(mn, a[t]);
        x = min_lane(mn);
        if (need == 1) break;
        IREALV eq = 0;
        for (int t = 0; t < KNN_LEVELS; ++t) {
            const IREALV e = a[t] == (IREALV)x;
            eq += e;
            a[t] = select(a[t], (IREALV)INF_BITS, e);
        }
        const uint c = count_lanes(eq);
        if (need <= c) break;
        need -= c;
    }
    return x <= m ? AS_REAL(x) : (REAL)NAN;
}

/* The reach of the walk of p (x relative to its 3-cell block, y and z to its cell, see
 * neighbors.h): the host's, cball.x (c^2, or less), or with extend (cball.x = c^2) the
 * radius of the largest ball around p inside its block of 27 cells, c plus p's distance
 * to the nearest face of its own cell (c to 1.5 c, ~1.125 c on average), less
 * KNN_REACH_SLACK epsilons of c for the coordinates' round-off (KNN_REACH_SLACK, the
 * host's clcurv/ops/knn_radius.py:REACH_SLACK), and never below c: every point within it is a
 * candidate of the walk, so a K-th found within it is exact. On a 1M-point uniform sphere
 * at the first cell (K = 30) the points left for the next level went from 8.6% to 1.8%.
 * As r^2. */
#ifndef KNN_REACH_SLACK
#error "knn_radius.cl needs KNN_REACH_SLACK (clcurv/ops/knn_radius.py:program_defines)"
#endif
#if REAL_IS_DOUBLE
#define REACH_EPS DBL_EPSILON
#else
#define REACH_EPS FLT_EPSILON
#endif
inline REAL reach2(REAL3 p, REAL2 cball, uint extend)
{
    const REAL c = cball.y;
    const REAL face = fmin(fmin(fmin(p.x - c, 2 * c - p.x), fmin(p.y, c - p.y)),
                           fmin(p.z, c - p.z));
    const REAL r = c + fmax(face, (REAL)0) - KNN_REACH_SLACK * REACH_EPS * c;
    return extend ? fmax(r * r, cball.x) : cball.x;
}

__kernel void kth_distance(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, __global const uint *cell_of,
                           __global const uint2 *ranges, const uint n, const REAL2 cball,
                           __global const REAL *prev, __global REAL *d2k, const uint extend)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    if (isfinite(prev[g])) { d2k[g] = prev[g]; return; }
    const uint co = cell_of[g];
    const uint cell = co & CELL_MASK;
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
    const REAL2 ball = (REAL2)(reach2(p, cball, extend), cball.y);
    IREALV a[KNN_LEVELS];                              /* per lane, ascending */
    for (int t = 0; t < KNN_LEVELS; ++t) a[t] = (IREALV)INF_BITS;
    IREALV lanes = 0;                                  /* minus the candidates per lane */
    IREALV b[KNN_BATCH];                               /* the latest chunks, b[0] newest */
    uint nb = 0;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        REALV d2;
        const IREALV m = chunk_d2(XA, Y, Z, i, end, pr, ball, &d2);
        lanes += m;
        for (int t = KNN_BATCH - 1; t > 0; --t) b[t] = b[t - 1];
        b[0] = select((IREALV)INF_BITS, AS_IREALV(d2), m);
        if (++nb == KNN_BATCH) {
            KNN_MERGE
            nb = 0;
        }
    NEIGHBOR_CHUNKS_END
    if (nb) {                                          /* the last chunks, INF for the rest */
        for (int t = 1; t < KNN_BATCH; ++t)
            if (t >= nb) b[t] = (IREALV)INF_BITS;
        KNN_MERGE
    }
    REAL d = (REAL)INFINITY;                           /* fewer than K within c */
    if (count_lanes(lanes) >= KNN_K) {
        d = kth_of_levels(a, lanes, ball.x, KNN_K);
        if (isnan(d)) {
            REAL buf[KNN_CAP + 1];           /* a scratch slot: append_lanes */
            d = kth_by_counting(XA, Y, Z, ranges, cell, p, ball, buf);
        }
    }
    d2k[g] = d;
}

#if REAL_IS_DOUBLE
#define REAL_MIN_NORMAL DBL_MIN
#else
#define REAL_MIN_NORMAL FLT_MIN
#endif

/* The balls' r^2 (sorted order, padded with PAD zeros) from the k-th d^2 of every point (no
 * point isolated): (sqrt(d^2) + slack)^2 (1 + MARGIN), at least the smallest normal REAL,
 * the operations of clcurv/ops/knn_radius.py:_margin (grow = 1 + MARGIN, exact in REAL; slack
 * the grids' round-off of a distance, ROUND_OFF eps of the last level's cell). */
__kernel void ball_r2(__global const REAL *d2, const uint n, const REAL grow,
                      const REAL slack, __global REAL *r2)
{
    const uint g = get_global_id(0);
    if (g < n) {
        const REAL d = sqrt(d2[g]) + slack;
        r2[g] = fmax(d * d * grow, REAL_MIN_NORMAL);
    } else if (g < n + PAD) r2[g] = 0;
}
