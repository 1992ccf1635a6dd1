/* knn.cl -- the orientation graph: k nearest neighbours with Hoppe-like weights
 * (clcurv/orient/graph.py drives it; its minimum spanning forest is forest.cl's).
 *
 * Points are the cloud's sorted points (clcurv/grid/binning.py); "input index" is order[g]. Normals
 * are the sorted SoA columns NX, NY, NZ of clcurv.grid.cloud.upload_sorted, a row of NaN for an
 * invalid normal (the host sets whole rows).
 *
 * Graph: nbr[g k + s], s < k, the sorted index of the s-th nearest other point with a valid
 * normal strictly within the radius, ordered by (squared distance, input index), NONE past
 * the last; wgt[g k + s] its edge weight (float)
 *     w = 1 - |n_g . n_j| + |d . n_g| |d . n_j| / |d|^2,   d = p_j - p_g   (0 when d = 0)
 * computed from the walk of the endpoint with the smaller input index, so both lists that
 * hold an edge hold the same bits (forest.cl relies on it: first_weight, next_weight take
 * the lightest edge of a point from its own list, whichever copy that is). In g's list that
 * is g's own walk when order[g] < order[j] (the lanes of the second pass, lane_weights),
 * else mirror_weight, from j's walk.
 */
#include "common.h"
#include "neighbors.h"
#include "radius.h"
#include "orient.h"

#define VSTOREV CAT(vstore, VW)

/* Squared-distance bins of the first pass of knn_graph: a point at squared distance d2 is in
 * bin min(floor(d2 NBIN / r^2), NBIN - 1) (monotone in d2, so the bins up to any one hold a
 * nearest-first prefix of the ball) */
#define NBIN 16
/* Most candidates the second pass collects (those in the bins up to the one reached by k);
 * a point with more (many coincident points) takes the insertion path instead */
#define MCAP 48                 /* a multiple of 16 */
#define CONVERT_FLOATV CAT(convert_float, VW)
#define CONVERT_IREALV CAT(convert_, IREALV)
#define FLOATV CAT(float, VW)
#define VSTOREF CAT(vstore, VW)

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

#define UINTV CAT(uint, VW)
#define CONVERT_UINTV CAT(convert_uint, VW)
#define CONVERT_INTV CAT(convert_int, VW)

/* The bin of each lane (see NBIN; s = NBIN / r^2; NaN -> the last bin) */
inline UINTV bin_of(REALV d2, REAL s)
{
    return CAT(as_uint, VW)(CONVERT_INTV(fmin(d2 * s, (REALV)(NBIN - 1))));
}

/* OR and sum of the lanes of a uint vector */
LANE_REDUCTION(or_lanes, uint, LANE_OR)
LANE_REDUCTION(hsum_ui, uint, LANE_ADD)



/* Bin counts packed 4 bits per bin in the lanes of lo (bins 0 .. 7) and hi (8 .. 15) (at
 * most 15 chunks' worth), as totals (one lane per bin) */
inline uint16 unpack_bins(UINTV lo, UINTV hi)
{
    /* 8-bit fields (at most 15 VW <= 240): the even bins of a half in e, the odd ones in o */
    const uint4 sh = (uint4)(0, 8, 16, 24);
    const uint4 el = ((uint4)hsum_ui(lo & (UINTV)0x0f0f0f0fu) >> sh) & (uint4)0xff;
    const uint4 ol = ((uint4)hsum_ui((lo >> 4) & (UINTV)0x0f0f0f0fu) >> sh) & (uint4)0xff;
    const uint4 eh = ((uint4)hsum_ui(hi & (UINTV)0x0f0f0f0fu) >> sh) & (uint4)0xff;
    const uint4 oh = ((uint4)hsum_ui((hi >> 4) & (UINTV)0x0f0f0f0fu) >> sh) & (uint4)0xff;
    return (uint16)(el.s0, ol.s0, el.s1, ol.s1, el.s2, ol.s2, el.s3, ol.s3,
                    eh.s0, oh.s0, eh.s1, oh.s1, eh.s2, oh.s2, eh.s3, oh.s3);
}

/* The ordering key of a neighbour: its squared distance (as float: for double precision
 * rounded, ties then broken by the index) above its input index. */
inline ulong nkey(REAL d2, uint input)
{
    return (ulong)as_uint((float)d2) << 32 | input;
}

/* The input indices of the lanes of the chunk at sorted index i */
inline UINTV lane_inputs(__global const uint *order, uint i, uint n)
{
    if (i + VW <= n) return CAT(vload, VW)(0, order + i);
    uint t[VW];                            /* the cloud's last chunk: order is not padded */
    for (uint l = 0; l < VW; ++l) t[l] = order[min(i + l, n - 1)];
    return CAT(vload, VW)(0, t);
}

/* The squared distances of the lanes as the high half of nkey: float bits, ordered as the
 * values (d2 >= 0) */
inline UINTV lane_dbits(REALV d2)
{
    return CAT(as_uint, VW)(CONVERT_FLOATV(d2));
}

/* The weight of the edge {g, j} (see the top) when order[j] < order[g]: from the offset of
 * j's walk, in which g lies in the mirrored row ((dz, dy) of g's row change sign), with the
 * products of lane_weights in the same order, so that both lists hold the same bits
 * (row: the row of g's walk in which j lies; p, ng: g's point and normal). */
inline float mirror_weight(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, __global const REAL *NX,
                           __global const REAL *NY, __global const REAL *NZ,
                           __global const uint *cell_of, uint n, REAL c, REAL3 p, REAL3 ng,
                           uint g, uint j, int row)
{
    const REAL sy = (REAL)(row % 3 - 1), sz = (REAL)(row / 3 - 1);
    __global const REAL *XA = x_rows(X, cell_of[j], n);
    const REAL3 d = (REAL3)(XA[g] - XA[j], p.y - (Y[j] + sy * c), p.z - (Z[j] + sz * c));
    const REAL3 na = (REAL3)(NX[j], NY[j], NZ[j]);
    const REAL d2 = dot3(d, d);
    const REAL t = d2 > 0 ? (fabs(dot3(d, na)) * fabs(dot3(d, ng))) / d2 : (REAL)0;
    const REAL w = ((REAL)1 - fabs(dot3(na, ng))) + t;
    return w > 0 ? (float)w : 0.0f;                    /* +0, never -0 */
}

/* The edge weights of the lanes (see the top) from the offsets d of g's walk, g's normal ng
 * and the lanes' normals nj, with dot3's roundings. */
inline FLOATV lane_weights(REALV dx, REALV dy, REALV dz, REAL3 ng, REALV njx, REALV njy,
                           REALV njz)
{
    const REALV d2 = sqdist(dx, dy, dz);
    const REALV a = fabs(fma(dz, (REALV)ng.z, fma(dy, (REALV)ng.y, dx * ng.x)));
    const REALV b = fabs(fma(dz, njz, fma(dy, njy, dx * njx)));
    const REALV t = select((REALV)0, (a * b) / d2, d2 > 0);
    const REALV nn = fma((REALV)ng.z, njz, fma((REALV)ng.y, njy, ng.x * njx));
    const REALV w = ((REALV)1 - fabs(nn)) + t;
    return select((FLOATV)0, CONVERT_FLOATV(w), CAT(convert_int, VW)(w > 0));   /* +0, never -0 */
}

/* The k nearest neighbours of every sorted point and their edge weights (see the top).
 *
 * Pass 1 counts the valid points of the ball in NBIN squared-distance bins (4-bit counters
 * packed in two uints per lane, emptied every 15 chunks); the first bin up to which at least k
 * others lie bounds the k-th distance. Pass 2 collects the (about k) others up to that bin
 * with their weights, and each one's rank among them (by (distance, input index)) is its
 * place in the list: no sorting. More than MCAP of them (coincident points): a bounded
 * insertion sort over the whole ball instead. The common path uses 32-bit vector lanes only:
 * 64-bit vector compares, shifts and float conversions are emulated on AVX2 CPUs and GPUs
 * (on a 2-core AMD EPYC, PoCL 3.1, 1M sphere, k = 10: 482 -> 319 ms with the same output
 * bits as the earlier ulong bins and keys). */
__kernel void knn_graph(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                        __global const REAL *NX, __global const REAL *NY,
                        __global const REAL *NZ, __global const uint *cell_of,
                        __global const uint2 *ranges, __global const uint *order,
                        const uint n, const REAL2 ball, const uint k,
                        __global uint *nbr, __global float *wgt, __global const REAL *W)
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
        const REAL3 ng = (REAL3)(NX[g], NY[g], NZ[g]);
        const uint og = order[g];
        /* the point's ball: the graph's radius, or with POINT_RADIUS its own (radius.h) */
        const REAL2 bl = POINT_BALL(W, g, ball);
        const REAL s = (REAL)NBIN / bl.x;
        REALV dx, dy, dz;
        UINTV lo = 0, hi = 0;              /* 4-bit counts of bins 0 .. 7, 8 .. 15 */
        UINTV rowor[9];                    /* per row, the bins its lanes met */
        for (int r = 0; r < 9; ++r)
            rowor[r] = 0;
        uint16 tot = 0;
        uint nch = 0;
        NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, bl, i, end, pr)
            IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
            const REALV d2 = sqdist(dx, dy, dz);
            m &= ~isnan(VLOADV(0, NX + i)) & isless(d2, (REALV)bl.x);
            const UINTV bn = bin_of(d2, s);
            const UINTV live = CAT(as_uint, VW)(CONVERT_INTV(m));
            const UINTV one = ((UINTV)1 << ((bn & (UINTV)7) << 2)) & live;
            const UINTV upper = (UINTV)0 - (bn >> 3);          /* all ones for bins 8 .. 15 */
            lo += one & ~upper;
            hi += one & upper;
            rowor[nb_z * 3 + nb_y] |= ((UINTV)1 << bn) & live;
            if (++nch == 15) {
                tot += unpack_bins(lo, hi);
                lo = hi = 0;
                nch = 0;
            }
        NEIGHBOR_CHUNKS_END
        tot += unpack_bins(lo, hi);
        /* the point itself is in bin 0 (d = 0) */
        uint c[NBIN];
        vstore16(tot, 0, c);
        c[0] -= 1;
        for (int b = 1; b < NBIN; ++b)
            c[b] += c[b - 1];
        uint bsel = NBIN - 1;
        uint below = c[NBIN - 1];
        for (int b = NBIN - 2; b >= 0; --b)
            if (c[b] >= k) { bsel = b; below = c[b]; }
        uint need = 0;                     /* the rows that hold a bin up to bsel */
        for (int r = 0; r < 9; ++r)
            need |= (uint)((or_lanes(rowor[r]) & ((2u << bsel) - 1)) != 0) << r;
        if (below <= MCAP) {
            /* the candidates' nkey as two 32-bit halves (AVX2 and GPUs have no 64-bit vector
               compare), rounded up to 16 for the ranks */
            uint kd[MCAP + 16], ki[MCAP + 16];
            uint ref[MCAP + 1];            /* the candidate's chunk slot * VW + lane */
            uint cbase[MCAP + 1];          /* per chunk slot: its first sorted index, row */
            uchar crow[MCAP + 1];
            float cw[(MCAP + 1) * VW];     /* per chunk slot: the lanes' weights */
            uint da[VW], ia[VW];
            IREAL ma[VW];
            uint nc = 0;
            NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, bl, i, end, pr)
                if (!(need >> (nb_z * 3 + nb_y) & 1)) break;    /* to the next row */
                IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
                const REALV d2 = sqdist(dx, dy, dz);
                m &= ~isnan(VLOADV(0, NX + i)) & isless(d2, (REALV)bl.x)
                     & CONVERT_IREALV(bin_of(d2, s) <= (UINTV)bsel)
                     & ((IREALV)(IREAL)(g - i) != LANES);
                if (any_lane(m)) {
                    CAT(vstore, VW)(lane_dbits(d2), 0, da);
                    CAT(vstore, VW)(lane_inputs(order, i, n), 0, ia);
                    VSTOREV(m, 0, ma);
                    VSTOREF(lane_weights(dx, dy, dz, ng, VLOADV(0, NX + i), VLOADV(0, NY + i),
                                         VLOADV(0, NZ + i)), nc, cw);
                    cbase[nc] = i;
                    crow[nc] = (uchar)(nb_z * 3 + nb_y);
                    for (uint l = 0; l < VW; ++l) {       /* branch-free append */
                        kd[cnt] = da[l];
                        ki[cnt] = ia[l];
                        ref[cnt] = nc * VW + l;
                        cnt = min(cnt + (uint)(ma[l] & 1), (uint)MCAP);
                    }
                    nc = min(nc + 1, (uint)MCAP);
                }
            NEIGHBOR_CHUNKS_END
            for (uint a = cnt; a < ((cnt + 15) & ~15u); ++a)
                kd[a] = ki[a] = 0;                    /* ranks past cnt are not used */
            for (uint a0 = 0; a0 < cnt; a0 += 16) {
                /* both halves < 2^31 (d2 >= 0 finite, input < 2^31): signed compares */
                const int16 db = as_int16(vload16(0, kd + a0)), ib = as_int16(vload16(0, ki + a0));
                int16 r16 = 0;                        /* -1 per key below each of (db, ib) */
                for (uint b = 0; b < cnt; ++b) {
                    const int16 d = (int16)(int)kd[b], e = (int16)(int)ki[b];
                    r16 += (db > d) | ((db == d) & (ib > e));
                }
                uint rk[16];
                vstore16(as_uint16(-r16), 0, rk);
                for (uint a = a0; a < min(a0 + 16, cnt); ++a) {
                    const uint r = rk[a - a0];
                    if (r < k) {
                        const uint c = ref[a] / VW, j = cbase[c] + ref[a] % VW;
                        out[r] = j;
                        outw[r] = ki[a] < og
                            ? mirror_weight(X, Y, Z, NX, NY, NZ, cell_of, n, ball.y, p, ng, g,
                                            j, crow[c])
                            : cw[ref[a]];
                    }
                }
            }
            cnt = min(cnt, k);
        } else {                           /* insertion over the whole ball, k kept */
            ulong key[KMAX];
            uint idx[KMAX];
            float wt[KMAX];
            uchar row[KMAX];
            REAL da[VW];
            float wa[VW];
            IREAL ma[VW];
            NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, bl, i, end, pr)
                IREALV m = lane_offsets(XA, Y, Z, i, end, pr, &dx, &dy, &dz);
                const REALV d2 = sqdist(dx, dy, dz);
                m &= ~isnan(VLOADV(0, NX + i)) & isless(d2, (REALV)bl.x);
                if (!any_lane(m)) continue;
                VSTOREV(d2, 0, da);
                VSTOREV(m, 0, ma);
                VSTOREF(lane_weights(dx, dy, dz, ng, VLOADV(0, NX + i), VLOADV(0, NY + i),
                                     VLOADV(0, NZ + i)), 0, wa);
                for (int l = 0; l < VW; ++l) {
                    const uint j = i + l;
                    if (!ma[l] || j == g) continue;
                    const ulong kc = nkey(da[l], order[j]);
                    int pos;
                    if (cnt < k) pos = cnt++;
                    else if (kc < key[k - 1]) pos = k - 1;
                    else continue;
                    while (pos > 0 && kc < key[pos - 1]) {
                        key[pos] = key[pos - 1]; idx[pos] = idx[pos - 1]; wt[pos] = wt[pos - 1];
                        row[pos] = row[pos - 1];
                        --pos;
                    }
                    key[pos] = kc; idx[pos] = j; wt[pos] = wa[l]; row[pos] = (uchar)(nb_z * 3 + nb_y);
                }
            NEIGHBOR_CHUNKS_END
            for (uint s = 0; s < cnt; ++s) {
                out[s] = idx[s];
                outw[s] = (uint)key[s] < og
                    ? mirror_weight(X, Y, Z, NX, NY, NZ, cell_of, n, ball.y, p, ng, g, idx[s],
                                    row[s])
                    : wt[s];
            }
        }
    }
    for (uint s = cnt; s < k; ++s) {
        out[s] = NONE;
        outw[s] = NAN;
    }
}
