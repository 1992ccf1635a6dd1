/* forest.cl -- the orientation graph (k nearest neighbours with Hoppe-like weights) and its
 * minimum spanning forest by Boruvka's algorithm, with every point's sign parity relative to
 * its component's root (clcurv/forest.py drives the kernels).
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
 * hold an edge hold the same bits. The edge list keeps each undirected edge once: in the
 * list of the endpoint with the smaller input index when both lists hold it.
 *
 * Edge lists: eu, ev (sorted indices, order[eu] < order[ev]) and ew (weight bits: weights are
 * >= +0, whose bits order like the floats). Edges are strictly ordered by (ew, order[eu],
 * order[ev]), so the minimum spanning forest is unique, and each round of Boruvka finds every
 * component's lightest edge with three passes of 32-bit atomic_min (weight, then the smaller
 * input index among the edges of that weight, then the larger). Atomics are used only for
 * min, whose result does not depend on the order of the updates: no result depends on the
 * work-group size or the scheduling. Edge kernels take blocks of B consecutive edges per
 * work-item; kept edges are compacted in order (per-block counts, a prefix sum).
 *
 * Components: comp[g] is the sorted index of g's root, par[g] g's sign parity relative to it
 * (1: g's normal must be negated to agree with the root's along the tree). A hook of root C
 * onto root D through the edge (u in C, v in D) is packed as link[C] = D << 1 | parity of C
 * relative to D, that parity being par[u] ^ (n_u . n_v < 0) ^ par[v]; pointer jumping
 * composes (root, parity) pairs by XOR.
 */
#include "common.h"
#include "neighbors.h"

#define NONE 0xffffffffu
/* longest neighbour list (clcurv/forest.py checks k against it: forest.KMAX) */
#define KMAX 32
#define VSTOREV CAT(vstore, VW)

/* a . b with its roundings spelled out (fma is exact then rounded once on every device), so
 * that no compiler's choice to contract a product and a sum changes a weight or a parity */
inline REAL dot3(REAL3 a, REAL3 b)
{
    return fma(a.z, b.z, fma(a.y, b.y, a.x * b.x));
}

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

/* Is slot s of sorted point g the kept copy of its undirected edge (see the top)? */
inline int slot_kept(__global const uint *nbr, __global const uint *order, uint k, uint g,
                     uint j)
{
    if (order[g] < order[j]) return 1;
    __global const uint *lj = nbr + (size_t)j * k;
    int found = 0;
    for (uint t = 0; t < k; ++t)            /* branch-free: the list is one or two lines */
        found |= lj[t] == g;
    return !found;
}

/* Kept slots of the points [b B, b B + B): counts[b]. */
__kernel void graph_count(__global const uint *nbr, __global const uint *order, const uint n,
                          const uint k, const uint B, __global uint *counts)
{
    const uint b = get_global_id(0);
    const uint g0 = b * B;
    if (g0 >= n) return;
    const uint g1 = min(g0 + B, n);
    uint c = 0;
    for (uint g = g0; g < g1; ++g)
        for (uint s = 0; s < k; ++s) {
            const uint j = nbr[(size_t)g * k + s];
            if (j == NONE) break;
            c += slot_kept(nbr, order, k, g, j);
        }
    counts[b] = c;
}

/* The kept slots of the points of block b as edges, from offsets[b] on. */
__kernel void graph_edges(__global const uint *nbr, __global const float *wgt,
                          __global const uint *order, const uint n, const uint k,
                          const uint B, __global const uint *offsets, __global uint *eu,
                          __global uint *ev, __global uint *ew)
{
    const uint b = get_global_id(0);
    const uint g0 = b * B;
    if (g0 >= n) return;
    const uint g1 = min(g0 + B, n);
    uint o = offsets[b];
    for (uint g = g0; g < g1; ++g)
        for (uint s = 0; s < k; ++s) {
            const size_t slot = (size_t)g * k + s;
            const uint j = nbr[slot];
            if (j == NONE) break;
            if (!slot_kept(nbr, order, k, g, j)) continue;
            const int lo_first = order[g] < order[j];
            eu[o] = lo_first ? g : j;
            ev[o] = lo_first ? j : g;
            ew[o] = as_uint(wgt[slot]);
            ++o;
        }
}

/* Exclusive prefix sum of counts[0 .. m) into offsets, the sum into total[0]. One work-item:
 * m is the number of blocks, a few ten thousand at most per 10^7 edges. */
__kernel void scan_blocks(__global const uint *counts, const uint m, __global uint *offsets,
                          __global uint *total)
{
    if (get_global_id(0) != 0) return;
    uint s = 0;
    for (uint b = 0; b < m; ++b) {
        offsets[b] = s;
        s += counts[b];
    }
    total[0] = s;
}

/* Lower *p to v (values only ever decrease within a pass, so a read that is already <= v
 * makes the atomic unnecessary). */
inline void lower(volatile __global uint *p, uint v)
{
    if (v < *p) atomic_min(p, v);
}

/* Pass 1 of a round: every component's lightest edge weight (bw), and the number of edges
 * of block b that join two components (counts[b]). */
__kernel void min_weight(__global const uint *eu, __global const uint *ev,
                         __global const uint *ew, const uint m, const uint B,
                         __global const uint *comp, volatile __global uint *bw,
                         __global uint *counts)
{
    const uint b = get_global_id(0);
    const uint e0 = b * B;
    if (e0 >= m) return;
    const uint e1 = min(e0 + B, m);
    uint c = 0;
    for (uint e = e0; e < e1; ++e) {
        const uint cu = comp[eu[e]], cv = comp[ev[e]];
        if (cu == cv) continue;
        ++c;
        const uint w = ew[e];
        lower(bw + cu, w);
        lower(bw + cv, w);
    }
    counts[b] = c;
}

/* Pass 2: the edges of block b that join two components, compacted to offsets[b] on in the
 * output lists, and each component's smallest input index order[eu] among its edges of the
 * lightest weight (blo). */
__kernel void min_lo(__global const uint *eu, __global const uint *ev, __global const uint *ew,
                     const uint m, const uint B, __global const uint *offsets,
                     __global const uint *comp, __global const uint *order,
                     __global const uint *bw, volatile __global uint *blo,
                     __global uint *eu2, __global uint *ev2, __global uint *ew2)
{
    const uint b = get_global_id(0);
    const uint e0 = b * B;
    if (e0 >= m) return;
    const uint e1 = min(e0 + B, m);
    uint o = offsets[b];
    for (uint e = e0; e < e1; ++e) {
        const uint u = eu[e], v = ev[e];
        const uint cu = comp[u], cv = comp[v];
        if (cu == cv) continue;
        const uint w = ew[e];
        eu2[o] = u; ev2[o] = v; ew2[o] = w;
        ++o;
        const int tu = w == bw[cu], tv = w == bw[cv];
        if (tu | tv) {
            const uint lo = order[u];
            if (tu) lower(blo + cu, lo);
            if (tv) lower(blo + cv, lo);
        }
    }
}

/* Pass 3: each component's largest-index endpoint order[ev] among its edges of weight bw
 * and smaller endpoint blo (bhi). */
__kernel void min_hi(__global const uint *eu, __global const uint *ev, __global const uint *ew,
                     const uint m, const uint B, __global const uint *comp,
                     __global const uint *order, __global const uint *bw,
                     __global const uint *blo, volatile __global uint *bhi)
{
    const uint b = get_global_id(0);
    const uint e0 = b * B;
    if (e0 >= m) return;
    const uint e1 = min(e0 + B, m);
    for (uint e = e0; e < e1; ++e) {
        const uint w = ew[e];
        const uint u = eu[e], v = ev[e];
        const uint cu = comp[u], cv = comp[v];
        const int tu = w == bw[cu], tv = w == bw[cv];
        if (tu | tv) {
            const uint lo = order[u];
            const int su = tu && lo == blo[cu], sv = tv && lo == blo[cv];
            if (su | sv) {
                const uint hi = order[v];
                if (su) lower(bhi + cu, hi);
                if (sv) lower(bhi + cv, hi);
            }
        }
    }
}

/* Every root g hooks onto the component across its lightest edge: link[g] = D << 1 | parity
 * of g relative to D (g << 1 for a root without edges); its edge goes to (flo, fhi) (input
 * indices). Resets the root's bw, blo, bhi for the next round. */
__kernel void hook(const uint n, __global const uint *comp, __global const uchar *par,
                   __global const uint *rank, __global const REAL *NX,
                   __global const REAL *NY, __global const REAL *NZ, __global uint *bw,
                   __global uint *blo, __global uint *bhi, __global uint *link,
                   __global uint *flo, __global uint *fhi)
{
    const uint g = get_global_id(0);
    if (g >= n || comp[g] != g) return;
    if (bw[g] == NONE) {
        link[g] = g << 1;
        return;
    }
    const uint lo = blo[g], hi = bhi[g];
    const uint a = rank[lo], b = rank[hi];
    const int a_in = comp[a] == g;
    const uint u = a_in ? a : b, v = a_in ? b : a;
    const uint pe = dot3((REAL3)(NX[a], NY[a], NZ[a]), (REAL3)(NX[b], NY[b], NZ[b])) < 0;
    link[g] = comp[v] << 1 | ((uint)par[u] ^ pe ^ (uint)par[v]);
    flo[g] = lo; fhi[g] = hi;
    bw[g] = NONE; blo[g] = NONE; bhi[g] = NONE;
}

/* Mutual hooks (C onto D and D onto C, through the same edge): the root with the smaller
 * input index stays a root. link -> link2; the edge of a root that stays one is dropped. */
__kernel void break_pairs(const uint n, __global const uint *comp, __global const uint *order,
                          __global const uint *link, __global uint *link2,
                          __global uint *flo)
{
    const uint g = get_global_id(0);
    if (g >= n || comp[g] != g) return;
    const uint L = link[g];
    const uint d = L >> 1;
    if (d != g && link[d] >> 1 == g && order[g] < order[d]) {
        link2[g] = g << 1;
        flo[g] = NONE;
    } else {
        link2[g] = L;
    }
}

/* Every root of the round to the end of its hook chain: B[g] = (final root, parity of g
 * relative to it), following A. A chain longer than chase stops at an intermediate root
 * (a correct pair) and lowers *unfinished to 0: then jump finishes. */
__kernel void resolve(const uint n, __global const uint *comp, __global const uint *A,
                      const uint chase, __global uint *B, volatile __global uint *unfinished)
{
    const uint g = get_global_id(0);
    if (g >= n || comp[g] != g) return;
    uint L = A[g];
    for (uint step = 0; ; ++step) {
        const uint L2 = A[L >> 1];
        if (L2 >> 1 == L >> 1) break;
        if (step == chase) {
            lower(unfinished, 0);
            break;
        }
        L = (L2 & ~1u) | ((L ^ L2) & 1u);
    }
    B[g] = L;
}

/* One step of pointer jumping over the roots of the round: B[g] = A[A[g]] with the parities
 * composed; *changed lowered to 0 when a link moved. */
__kernel void jump(const uint n, __global const uint *comp, __global const uint *A,
                   __global uint *B, volatile __global uint *changed)
{
    const uint g = get_global_id(0);
    if (g >= n || comp[g] != g) return;
    const uint L = A[g];
    const uint L2 = A[L >> 1];
    B[g] = (L2 & ~1u) | ((L ^ L2) & 1u);
    if (L2 >> 1 != L >> 1) lower(changed, 0);
}

/* Every point to its new root: comp[g] from the old root's final link, parities composed. */
__kernel void relabel(const uint n, __global uint *comp, __global uchar *par,
                      __global const uint *A)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const uint L = A[comp[g]];
    comp[g] = L >> 1;
    par[g] ^= (uchar)(L & 1u);
}

/* Initial state: every point its own root, rank = inverse of order, no best edges. */
__kernel void forest_init(const uint n, __global const uint *order, __global uint *comp,
                          __global uchar *par, __global uint *rank, __global uint *bw,
                          __global uint *blo, __global uint *bhi, __global uint *flo)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    comp[g] = g; par[g] = 0;
    rank[order[g]] = g;
    bw[g] = NONE; blo[g] = NONE; bhi[g] = NONE; flo[g] = NONE;
}

/* Results in input order: the root's input index (NONE for an invalid normal), the parity,
 * and the forest edge by which a point's component hooked, at the point's input index (NONE
 * where none). */
__kernel void forest_out(const uint n, __global const uint *order, __global const REAL *NX,
                         __global const uint *comp, __global const uchar *par,
                         __global const uint *flo, __global const uint *fhi,
                         __global uint *label, __global uchar *parity, __global uint *elo,
                         __global uint *ehi)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const uint i = order[g];
    const int ok = !isnan(NX[g]);
    label[i] = ok ? order[comp[g]] : NONE;
    parity[i] = ok ? par[g] : 0;
    elo[i] = flo[g];
    ehi[i] = fhi[g];
}
