/* knn.cl -- the orientation graph: k nearest neighbours with Hoppe-like weights
 * (clcurv/graph.py drives it; its minimum spanning forest is forest.cl's).
 *
 * Points are the cloud's sorted points (clcurv/grid.py); "input index" is order[g]. Normals
 * are the sorted SoA columns NX, NY, NZ of clcurv.cloud.upload_sorted, a row of NaN for an
 * invalid normal (the host sets whole rows).
 *
 * Graph: nbr[g k + s], s < k, the sorted index of the s-th nearest other point with a valid
 * normal strictly within the radius, ordered by (squared distance, input index), NONE past
 * the last; wgt[g k + s] its edge weight (float)
 *     w = 1 - |n_g . n_j| + |d . n_g| |d . n_j| / |d|^2,   d = p_j - p_g   (0 when d = 0)
 * computed from the walk of the endpoint with the smaller input index, so both lists that
 * hold an edge hold the same bits.
 */
#include "common.h"
#include "neighbors.h"
#include "orient.h"

#define VSTOREV CAT(vstore, VW)

/* Squared-distance bins of the first pass of knn_graph: bin b holds d^2 < r^2 (b + 1) / NBIN */
#define NBIN 8
/* Most candidates the second pass collects (those below the bin edge reached by k); a point
 * with more (many coincident points) takes the insertion path instead */
#define MCAP 48                 /* a multiple of 16 */
#define FLOATV CAT(float, VW)
#define VSTOREF CAT(vstore, VW)
#define KEY_NONE 0xffffffffffffffffUL

/* Offsets q - p of the chunk at i as seen from a row (pr, neighbors.h) and its live lanes
 * (the ball test is the caller's, on sqdist, so both passes see the same numbers). */
inline IREALV lane_offsets(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, uint i, uint end, REAL3 pr,
                           REALV *dx, REALV *dy, REALV *dz)
{
    *dx = VLOADV(0, X + i) - pr.x;
    *dy = VLOADV(0, Y + i) - pr.y;
    *dz = VLOADV(0, Z + i) - pr.z;
    return LANES < (IREALV)((IREAL)(end - i));
}

inline REALV sqdist(REALV dx, REALV dy, REALV dz)
{
    return fma(dz, dz, fma(dy, dy, dx * dx));
}

/* The ordering key of a neighbour: its squared distance (as float: for double precision
 * rounded, ties then broken by the index) above its input index. */
inline ulong nkey(REAL d2, uint input)
{
    return (ulong)as_uint((float)d2) << 32 | input;
}

/* The weight of the edge {g, j} (see the top), symmetric to the bit: the offset is the one
 * the walk of the endpoint with the smaller input index computes (row: the row of the walk
 * of g in which j lies). */
inline float edge_weight(__global const REAL *X, __global const REAL *Y,
                         __global const REAL *Z, __global const REAL *NX,
                         __global const REAL *NY, __global const REAL *NZ,
                         __global const uint *cell_of, __global const uint *order, uint n,
                         REAL c, uint g, uint j, int row)
{
    const int gfirst = order[g] < order[j];
    const uint a = gfirst ? g : j, b = gfirst ? j : g;
    /* rows are mirrored from b's walk to a's: (dz, dy) of the row change sign */
    const REAL sy = (REAL)(gfirst ? 1 - row % 3 : row % 3 - 1);
    const REAL sz = (REAL)(gfirst ? 1 - row / 3 : row / 3 - 1);
    __global const REAL *XA = x_rows(X, cell_of[a], n);
    const REAL3 d = (REAL3)(XA[b] - XA[a], Y[b] - (Y[a] + sy * c), Z[b] - (Z[a] + sz * c));
    const REAL3 na = (REAL3)(NX[a], NY[a], NZ[a]), nb = (REAL3)(NX[b], NY[b], NZ[b]);
    const REAL d2 = dot3(d, d);
    const REAL t = d2 > 0 ? (fabs(dot3(d, na)) * fabs(dot3(d, nb))) / d2 : (REAL)0;
    const REAL w = ((REAL)1 - fabs(dot3(na, nb))) + t;
    return w > 0 ? (float)w : 0.0f;                    /* +0, never -0 */
}

/* The k nearest neighbours of every sorted point and their edge weights (see the top).
 *
 * Pass 1 counts the valid points of the ball in NBIN squared-distance bins; the first bin
 * edge e below which at least k others lie bounds the k-th distance. Pass 2 collects the
 * (about k) others below e, and each one's rank among them (by (distance, input index)) is
 * its place in the list: no sorting. More than MCAP below e (coincident points): a
 * bounded insertion sort over the whole ball instead. */
__kernel void knn_graph(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                        __global const REAL *NX, __global const REAL *NY,
                        __global const REAL *NZ, __global const uint *cell_of,
                        __global const uint2 *ranges, __global const uint *order,
                        const uint n, const REAL2 ball, const uint k,
                        __global uint *nbr, __global float *wgt)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    __global uint *out = nbr + (size_t)g * k;
    __global float *outw = wgt + (size_t)g * k;
    uint cnt = 0;
    if (!isnan(NX[g])) {
        const uint co = cell_of[g];
        __global const REAL *XA = x_rows(X, co, n);
        const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
        REALV dx, dy, dz;
        REALV hist[NBIN];
        REAL edge[NBIN];
        for (int b = 0; b < NBIN; ++b) {
            hist[b] = 0;
            edge[b] = ball.x * (REAL)(b + 1) / (REAL)NBIN;
        }
        edge[NBIN - 1] = ball.x;
        NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
            IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
            const REALV d2 = sqdist(dx, dy, dz);
            m &= ~isnan(VLOADV(0, NX + i));
            for (int b = 0; b < NBIN; ++b)
                hist[b] += select((REALV)0, (REALV)1, m & isless(d2, (REALV)edge[b]));
        NEIGHBOR_CHUNKS_END
        /* the point itself is in every bin (d = 0) */
        REAL e = ball.x;
        uint below = (uint)hsum(hist[NBIN - 1]) - 1;
        for (int b = NBIN - 2; b >= 0; --b) {
            const uint c = (uint)hsum(hist[b]) - 1;
            if (c >= k) { e = edge[b]; below = c; }
        }
        if (below <= MCAP) {
            ulong key[MCAP + 16];          /* rounded up to 16 with KEY_NONE for the ranks */
            uint idx[MCAP + 1];
            uchar row[MCAP + 1];
            REAL da[VW];
            IREAL ma[VW];
            NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
                IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
                const REALV d2 = sqdist(dx, dy, dz);
                m &= ~isnan(VLOADV(0, NX + i)) & isless(d2, (REALV)e);
                if (any(m)) {
                    VSTOREV(d2, 0, da);
                    VSTOREV(m, 0, ma);
                    const uchar rw = (uchar)(nb_z * 3 + nb_y);
                    for (int l = 0; l < VW; ++l) {        /* branch-free append */
                        const uint j = i + l;
                        key[cnt] = nkey(da[l], order[min(j, n - 1)]);
                        idx[cnt] = j;
                        row[cnt] = rw;
                        cnt = min(cnt + (uint)(ma[l] != 0 && j != g), (uint)MCAP);
                    }
                }
            NEIGHBOR_CHUNKS_END
            for (uint a = cnt; a < ((cnt + 15) & ~15u); ++a)
                key[a] = KEY_NONE;
            for (uint a = 0; a < cnt; ++a) {
                const ulong16 ka = (ulong16)key[a];
                long16 below16 = 0;                  /* -1 per key < key[a] */
                for (uint b = 0; b < cnt; b += 16)
                    below16 += ka > vload16(0, key + b);
                const long8 s8 = below16.lo + below16.hi;
                const long4 s4 = s8.lo + s8.hi;
                const long2 s2 = s4.lo + s4.hi;
                const uint rk = (uint)(-(s2.x + s2.y));
                if (rk < k) {
                    out[rk] = idx[a];
                    outw[rk] = edge_weight(X, Y, Z, NX, NY, NZ, cell_of, order, n, ball.y, g,
                                           idx[a], row[a]);
                }
            }
            cnt = min(cnt, k);
        } else {                           /* insertion over the whole ball, k kept */
            ulong key[KMAX];
            uint idx[KMAX];
            uchar row[KMAX];
            REAL da[VW];
            IREAL ma[VW];
            NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
                IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
                const REALV d2 = sqdist(dx, dy, dz);
                m &= ~isnan(VLOADV(0, NX + i)) & isless(d2, (REALV)ball.x);
                VSTOREV(d2, 0, da);
                VSTOREV(m, 0, ma);
                for (int l = 0; l < VW; ++l) {
                    const uint j = i + l;
                    if (!ma[l] || j == g) continue;
                    const ulong kc = nkey(da[l], order[j]);
                    int pos;
                    if (cnt < k) pos = cnt++;
                    else if (kc < key[k - 1]) pos = k - 1;
                    else continue;
                    while (pos > 0 && kc < key[pos - 1]) {
                        key[pos] = key[pos - 1]; idx[pos] = idx[pos - 1]; row[pos] = row[pos - 1];
                        --pos;
                    }
                    key[pos] = kc; idx[pos] = j; row[pos] = (uchar)(nb_z * 3 + nb_y);
                }
            NEIGHBOR_CHUNKS_END
            for (uint s = 0; s < cnt; ++s) {
                out[s] = idx[s];
                outw[s] = edge_weight(X, Y, Z, NX, NY, NZ, cell_of, order, n, ball.y, g,
                                      idx[s], row[s]);
            }
        }
    }
    for (uint s = cnt; s < k; ++s) {
        out[s] = NONE;
        outw[s] = NAN;
    }
}
