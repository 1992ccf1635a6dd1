/* knn_radius.cl -- the squared distance of every point to its K-th nearest point (the point
 * itself the first), on the grid of a DeviceCloud: the k-NN radius (clcurv/knn_radius.py).
 *
 * One work-item per sorted point; the same fixed-order walk over the 27 cells as the
 * operators (neighbors.h), the candidates within the cloud's cell c (open ball d^2 < c^2).
 * The K smallest d^2 are kept sorted in a private array (insertion from the end); a lane
 * enters only when it is below the current K-th smallest (or while fewer than K are kept).
 * d^2 is computed as chunk_offsets computes it, so an operator's ball test d^2 < r^2 at
 * r^2 = d2k (1 + a few ulps) (the host's margin) holds exactly the K points.
 * Output d2k[g] (sorted order): the K-th smallest d^2, or +INFINITY when fewer than K
 * points lie within c (the host then bins at a larger cell).
 * Build option: KNN_K (1 .. clcurv.knn_radius.MAX_K).
 */
#include "common.h"
#include "neighbors.h"

#if !defined(KNN_K) || KNN_K < 1
#error "knn_radius.cl needs KNN_K (clcurv/knn_radius.py)"
#endif

__kernel void kth_distance(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, __global const uint *cell_of,
                           __global const uint2 *ranges, const uint n, const REAL2 ball,
                           __global REAL *d2k)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const uint co = cell_of[g];
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
    REAL best[KNN_K];
    uint cnt = 0;
    REAL thr = ball.x;                  /* below it a candidate enters the K best */
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(XA, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV d2 = dx * dx + dy * dy + dz * dz;
        const IREALV in = m & isless(d2, (REALV)thr);
        REAL dl[VW];
        IREAL il[VW];
        CAT(vstore, VW)(d2, 0, dl);
        CAT(vstore, VW)(in, 0, il);
        for (int l = 0; l < VW; ++l) {
            if (!il[l]) continue;
            const REAL v = dl[l];
            if (cnt == KNN_K && !(v < best[KNN_K - 1])) continue;
            int j = cnt < KNN_K ? (int)cnt++ : KNN_K - 1;
            while (j > 0 && best[j - 1] > v) { best[j] = best[j - 1]; --j; }
            best[j] = v;
        }
        if (cnt == KNN_K) thr = best[KNN_K - 1];
    NEIGHBOR_CHUNKS_END
    d2k[g] = cnt == KNN_K ? best[KNN_K - 1] : (REAL)INFINITY;
}
