/* scale_space.cl -- one iteration of the MLS1 scale space (Digne & Morel, Theorem 5): every
 * point moves to its projection on the weighted PCA plane of its ball, all points together
 * from the previous iterate (ping-pong buffers, sorted order).
 *
 * The grid (cells, ranges) was built on the binned positions B with a cell size h > r; the
 * candidate set of a point is exact as long as every point drifted less than (h - r) / 2
 * from B. Each step writes the drift |x' - B| per point; block_max reduces it so that the
 * host re-bins only when that bound is crossed. Points with too few neighbours or a
 * degenerate ball stay where they are. D accumulates the displacement from the input (small
 * numbers, so the final positions keep the input's float64 digits on the host).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"

/* One work-item per VW consecutive sorted points of [first, stop) (global size >=
 * ceil((stop - first) / VW)); drift[g - first]: the drift buffer holds one chunk. */
__kernel void mls1_step(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                        __global const REAL *W, __global const uint *cell_of,
                        __global const uint2 *ranges, const uint n, const REAL2 ball,
                        __global const REAL *BX, __global const REAL *BY, __global const REAL *BZ,
                        __global REAL *XN, __global REAL *YN, __global REAL *ZN,
                        __global REAL *DX, __global REAL *DY, __global REAL *DZ,
                        const uint first, const uint stop, __global REAL *drift)
{
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, 0, cell_of, ranges, n, g0, kn, ball, (REAL)0, &pb);
    for (uint k = 0; k < kn; ++k) {
        const uint g = g0 + k;
        REAL3 move = (REAL3)(0);
        if (pca_status(&pb, k, MIN_COUNT_PCA) == ST_OK) {
            const REAL3 v0 = (REAL3)(pb.v0x[k], pb.v0y[k], pb.v0z[k]);
            move = dot((REAL3)(pb.mux[k], pb.muy[k], pb.muz[k]), v0) * v0;
        }
        const REAL3 q = (REAL3)(X[g], Y[g], Z[g]) + move;       /* x in alignment 0 */
        for (uint a = 0; a < 3; ++a) {                          /* every copy of x moves */
            const size_t ga = (size_t)a * (n + PAD) + g;
            XN[ga] = X[ga] + move.x;
        }
        YN[g] = q.y; ZN[g] = q.z;
        DX[g] += move.x; DY[g] += move.y; DZ[g] += move.z;
        drift[g - first] = length(q - (REAL3)(BX[g], BY[g], BZ[g]));
    }
}
/* Maximum of each block of `block` consecutive values (fixed order, no atomics). */
__kernel void block_max(__global const REAL *v, const uint n, const uint block,
                        __global REAL *out, const uint nblocks)
{
    const uint b = get_global_id(0);
    if (b >= nblocks) return;
    const uint s = b * block, e = min(s + block, n);
    REAL m = 0;
    for (uint i = s; i < e; ++i) m = fmax(m, v[i]);
    out[b] = m;
}
