/* knn_radius.cl -- the squared distance of every point to its K-th nearest point (the point
 * itself the first), on the grid of a DeviceCloud: the k-NN radius (clcurv/knn_radius.py).
 *
 * One work-item per sorted point; the same fixed-order walk over the 27 cells as the
 * operators (neighbors.h), the candidates within the cloud's cell c (open ball d^2 < c^2).
 * The K-th smallest d^2 is selected by narrowing an interval [lo, hi) of d^2 that holds it
 * (first [0, c^2)): a counting pass splits it into NBIN bins (vector compares, no branch)
 * and keeps the bin where the count reaches the rank sought; once that bin holds at most
 * KNN_CAP candidates, a last pass gathers them and an insertion sort picks the rank. A bin
 * that cannot be narrowed further (many equal distances: duplicates) gives its upper end.
 * Points whose prev[g] is finite (found at a smaller cell, sorted order of this cloud) are
 * copied, not walked again.
 * Output d2k[g] (sorted order): the K-th smallest d^2, or +INFINITY when fewer than K
 * points lie within c (the host then bins at a larger cell).
 * Build option: KNN_K (1 .. clcurv.knn_radius.MAX_K).
 */
#include "common.h"
#include "neighbors.h"

#if !defined(KNN_K) || KNN_K < 1
#error "knn_radius.cl needs KNN_K (clcurv/knn_radius.py)"
#endif

#define NBIN 8              /* bins per counting pass */
#define KNN_CAP 64          /* candidates gathered by the last pass */
#define KNN_ROUNDS 12       /* counting passes at most (each narrows the interval 8x) */

/* d^2 of the chunk's lanes (as chunk_offsets) and the mask of those in the open ball. */
inline IREALV chunk_d2(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                       uint i, uint end, REAL3 pr, REAL2 ball, REALV *d2)
{
    REALV dx, dy, dz;
    const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
    *d2 = dx * dx + dy * dy + dz * dz;
    return m;
}

__kernel void kth_distance(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, __global const uint *cell_of,
                           __global const uint2 *ranges, const uint n, const REAL2 ball,
                           __global const REAL *prev, __global REAL *d2k)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    if (isfinite(prev[g])) { d2k[g] = prev[g]; return; }
    const uint co = cell_of[g];
    const uint cell = co & CELL_MASK;
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
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
        if (b == NBIN) { d2k[g] = (REAL)INFINITY; return; }   /* fewer than K within c */
        const REAL nlo = b ? edge[b - 1] : lo, nhi = edge[b];
        need -= below;
        if (inside <= KNN_CAP || !(nlo < nhi)) { lo = nlo; hi = nhi; break; }
        if (nlo == lo && nhi == hi) break;                   /* cannot narrow: ties */
        lo = nlo; hi = nhi;
    }
    if (inside > KNN_CAP) { d2k[g] = hi; return; }          /* equal distances: its end */
    /* gather the candidates of [lo, hi) and pick the need-th smallest */
    REAL buf[KNN_CAP];
    uint got = 0;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        REALV d2;
        const IREALV m = chunk_d2(XA, Y, Z, i, end, pr, ball, &d2)
                         & isgreaterequal(d2, (REALV)lo) & isless(d2, (REALV)hi);
        if (hsum(select((REALV)0, (REALV)1, m)) > 0) {
            REAL dl[VW];
            IREAL ml[VW];
            CAT(vstore, VW)(d2, 0, dl);
            CAT(vstore, VW)(m, 0, ml);
            for (int l = 0; l < VW; ++l) {
                if (!ml[l] || got >= KNN_CAP) continue;
                int j = (int)got++;
                while (j > 0 && buf[j - 1] > dl[l]) { buf[j] = buf[j - 1]; --j; }
                buf[j] = dl[l];
            }
        }
    NEIGHBOR_CHUNKS_END
    d2k[g] = buf[need - 1];
}
