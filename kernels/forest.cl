/* forest.cl -- the minimum spanning forest of the orientation graph (knn.cl) by Boruvka's
 * algorithm, with every point's sign parity relative to
 * its component's root (clcurv/orient/forest.py drives the kernels).
 *
 * Points are the cloud's sorted points (clcurv/grid/binning.py); "input index" is order[g]. Normals
 * are the sorted SoA columns NX, NY, NZ of clcurv.grid.cloud.upload_sorted, a row of NaN for an
 * invalid normal (the host sets whole rows).
 *
 * The graph is knn.cl's: nbr[g k + s] and wgt[g k + s] (NONE past a list's end). An edge
 * held by both lists has the same weight bits in both (knn.cl computes it from the smaller
 * input index's side), so the kernels may meet it twice: no minimum changes.
 *
 * Edge lists: eu, ev (sorted indices, order[eu] < order[ev]) and ew (weight bits: weights are
 * >= +0, whose bits order like the floats). Edges are strictly ordered by (ew, order[eu],
 * order[ev]), so the minimum spanning forest is unique, and each round of Boruvka finds every
 * component's lightest edge with three passes of 32-bit atomic_min (weight, then the smaller
 * input index among the edges of that weight, then the larger). Atomics are used only for
 * min, whose result does not depend on the order of the updates: no result depends on the
 * work-group size or the scheduling. Rounds 1 and 2 read the neighbour lists (first_*,
 * next_*); round 2 writes the edge list of the edges that still join two components (one
 * per pair of components, mostly), and later rounds compact it. Kernels take blocks of B
 * consecutive points per work-item; a block's edges are compacted in place, in order.
 *
 * Components: comp[g] is the sorted index of g's root, par[g] g's sign parity relative to it
 * (1: g's normal must be negated to agree with the root's along the tree). A hook of root C
 * onto root D through the edge (u in C, v in D) is packed as link[C] = D << 1 | parity of C
 * relative to D, that parity being par[u] ^ (n_u . n_v < 0) ^ par[v]; pointer jumping
 * composes (root, parity) pairs by XOR.
 */
#include "common.h"
#include "orient.h"

/* The sum of counts[0 .. m) into total[0] (one work-item). */
__kernel void total(__global const uint *counts, const uint m, __global uint *total)
{
    if (get_global_id(0) != 0) return;
    uint s = 0;
    for (uint b = 0; b < m; ++b) s += counts[b];
    total[0] = s;
}

/* Lower *p to v (values only ever decrease within a pass, so a read that is already <= v
 * makes the atomic unnecessary). */
inline void lower(volatile __global uint *p, uint v)
{
    if (v < *p) atomic_min(p, v);
}

/* The edge list is kept in blocks: block b's live edges are [b stride, b stride +
 * counts[b]), written by next_edges from block b of the points. Edges are written through a
 * small table of component pairs (PAIRS entries, direct mapped): of two edges that join the
 * same two components only the lighter one (in the strict order) is kept, as the other can
 * never be a component's lightest edge, in this round or a later one. A block's edges are
 * written back in place (the write position never passes the read position). */
#define PAIRS_LOG2 6
#define PAIRS (1u << PAIRS_LOG2)

typedef struct {
    uint cu[PAIRS], cv[PAIRS], u[PAIRS], v[PAIRS], w[PAIRS];
} pair_table;

/* Is edge (w, u, v) lighter than entry h (u, v: order[u] < order[v])? */
inline int lighter(const pair_table *t, uint h, uint w, uint u, uint v,
                   __global const uint *order)
{
    if (w != t->w[h]) return w < t->w[h];
    const uint a = order[u], a2 = order[t->u[h]];
    return a != a2 ? a < a2 : order[v] < order[t->v[h]];
}

/* Writes entry h at *o (and lowers both components' bw when push). */
inline void emit(const pair_table *t, uint h, size_t *o, __global uint *eu, __global uint *ev,
                 __global uint *ew, volatile __global uint *bw, int push)
{
    eu[*o] = t->u[h]; ev[*o] = t->v[h]; ew[*o] = t->w[h];
    ++*o;
    if (push) {
        lower(bw + t->cu[h], t->w[h]);
        lower(bw + t->cv[h], t->w[h]);
    }
}

/* Puts edge (u, v, w) between components cu != cv into the table (evicting another pair's
 * edge to *o). */
inline void put(pair_table *t, uint cu, uint cv, uint u, uint v, uint w, size_t *o,
                __global uint *eu, __global uint *ev, __global uint *ew,
                volatile __global uint *bw, int push, __global const uint *order)
{
    const uint a = min(cu, cv), c = max(cu, cv);
    const uint h = ((a * 0x9e3779b1u) ^ (c * 0x85ebca77u)) >> (32 - PAIRS_LOG2);
    if (t->cu[h] == a && t->cv[h] == c) {
        if (!lighter(t, h, w, u, v, order)) return;
    } else if (t->cu[h] != NONE) {
        emit(t, h, o, eu, ev, ew, bw, push);
    }
    t->cu[h] = a; t->cv[h] = c; t->u[h] = u; t->v[h] = v; t->w[h] = w;
}

inline void clear(pair_table *t)
{
    for (uint h = 0; h < PAIRS; ++h) t->cu[h] = NONE;
}

inline void flush(const pair_table *t, size_t *o, __global uint *eu, __global uint *ev,
                  __global uint *ew, volatile __global uint *bw, int push)
{
    for (uint h = 0; h < PAIRS; ++h)
        if (t->cu[h] != NONE) emit(t, h, o, eu, ev, ew, bw, push);
}

/* Pass 1 of a round: every component's lightest edge weight (bw); the edges of block b that
 * join two components, one per pair of components, moved to the block's start (counts[b]). */
__kernel void min_weight(__global uint *eu, __global uint *ev, __global uint *ew,
                         const uint nb, const uint stride, __global uint *counts,
                         __global const uint *comp, __global const uint *order,
                         volatile __global uint *bw)
{
    const uint b = get_global_id(0);
    if (b >= nb) return;
    const size_t e0 = (size_t)b * stride, e1 = e0 + counts[b];
    if (e0 == e1) return;
    pair_table t;
    clear(&t);
    size_t o = e0;
    for (size_t e = e0; e < e1; ++e) {
        const uint u = eu[e], v = ev[e];
        const uint cu = comp[u], cv = comp[v];
        if (cu == cv) continue;
        put(&t, cu, cv, u, v, ew[e], &o, eu, ev, ew, bw, 1, order);
    }
    flush(&t, &o, eu, ev, ew, bw, 1);
    counts[b] = (uint)(o - e0);
}

/* Pass 2: each component's smallest input index order[eu] among its edges of the lightest
 * weight (blo). */
__kernel void min_lo(__global const uint *eu, __global const uint *ev, __global const uint *ew,
                     const uint nb, const uint stride, __global const uint *counts,
                     __global const uint *comp, __global const uint *order,
                     __global const uint *bw, volatile __global uint *blo)
{
    const uint b = get_global_id(0);
    if (b >= nb) return;
    const size_t e0 = (size_t)b * stride, e1 = e0 + counts[b];
    for (size_t e = e0; e < e1; ++e) {
        const uint u = eu[e], v = ev[e];
        const uint cu = comp[u], cv = comp[v];
        const uint w = ew[e];
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
                     const uint nb, const uint stride, __global const uint *counts,
                     __global const uint *comp, __global const uint *order,
                     __global const uint *bw, __global const uint *blo,
                     volatile __global uint *bhi)
{
    const uint b = get_global_id(0);
    if (b >= nb) return;
    const size_t e0 = (size_t)b * stride, e1 = e0 + counts[b];
    for (size_t e = e0; e < e1; ++e) {
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

/* Rounds 1 and 2 read the neighbour lists directly. An undirected edge is met in every list
 * that holds it, with the same weight bits and the same (smaller, larger input index) pair,
 * so meeting it twice changes no minimum. A slot g -> j updates both endpoints; g's own
 * list is reduced in registers first. Round 2 writes the edge list (next_edges).
 *
 * Round 1: every point is its own component; among the edges of g of weight bw[g] the
 * order (smaller, larger input index) is the order of the other endpoint's input index, so
 * two passes suffice: the weights (bw; and fmask: bit s set when order[g] is the smaller
 * input index of slot s), then the other endpoint (into bhi). */
__kernel void first_weight(__global const uint *nbr, __global const float *wgt,
                           __global const uint *order, const uint n, const uint k,
                           const uint B, volatile __global uint *bw, __global uint *fmask,
                           __global uint *own_w, __global uint *own_o, __global uint *own_j)
{
    const uint b = get_global_id(0);
    const uint g0 = b * B;
    if (g0 >= n) return;
    const uint g1 = min(g0 + B, n);
    /* the block's own minima first: then a slot g -> j of an edge that j's list holds too
     * finds bw[j] <= its weight already (when j is in this block or done), and most of the
     * second loop's lower() calls are a read, not an atomic */
    for (uint g = g0; g < g1; ++g) {
        const uint og = order[g];
        uint mw = NONE, mo = NONE, mj = NONE, fm = 0;
        for (uint s = 0; s < k; ++s) {
            const size_t slot = (size_t)g * k + s;
            const uint j = nbr[slot];
            if (j == NONE) break;
            const uint w = as_uint(wgt[slot]), oj = order[j];
            fm |= (uint)(og < oj) << s;
            const int better = w < mw || (w == mw && oj < mo);
            mo = better ? oj : mo;
            mj = better ? j : mj;
            mw = min(mw, w);
        }
        fmask[g] = fm;
        own_w[g] = mw; own_o[g] = mo; own_j[g] = mj;
        if (mw != NONE) lower(bw + g, mw);
    }
    for (uint g = g0; g < g1; ++g)
        for (uint s = 0; s < k; ++s) {
            const size_t slot = (size_t)g * k + s;
            const uint j = nbr[slot];
            if (j == NONE) break;
            lower(bw + j, as_uint(wgt[slot]));
        }
}

/* own_w, own_o: the lightest edge of g's own list (weight, other endpoint's input index). */
__kernel void first_other(__global const uint *nbr, __global const float *wgt,
                          __global const uint *order,
                          __global const uint *own_w, __global const uint *own_o,
                          const uint n, const uint k, const uint B, __global const uint *bw,
                          volatile __global uint *bhi)
{
    const uint b = get_global_id(0);
    const uint g0 = b * B;
    if (g0 >= n) return;
    const uint g1 = min(g0 + B, n);
    /* own lists first, as in first_weight: the other copy of an edge then mostly finds
     * bhi already at its value */
    for (uint g = g0; g < g1; ++g) {
        const uint mw = own_w[g];
        if (mw != NONE && mw == bw[g]) lower(bhi + g, own_o[g]);
    }
    for (uint g = g0; g < g1; ++g) {
        const uint og = order[g];
        for (uint s = 0; s < k; ++s) {
            const size_t slot = (size_t)g * k + s;
            const uint j = nbr[slot];
            if (j == NONE) break;
            if (as_uint(wgt[slot]) == bw[j]) lower(bhi + j, og);
        }
    }
}

/* Round 2, pass 1: the slots of the points of block b that join two components go through
 * the pair table to the block's edges [b stride, b stride + counts[b]); bw is lowered by
 * every edge written (min_lo and min_hi follow on the edges). Both slots of an edge held by
 * both lists go in (the table usually merges them; an edge met twice changes no minimum). */
__kernel void next_edges(__global const uint *nbr, __global const float *wgt,
                         __global const uint *order, __global const uint *fmask,
                         __global const uint *comp, const uint n,
                         const uint k, const uint B, const uint stride,
                         __global uint *counts, volatile __global uint *bw,
                         __global uint *eu, __global uint *ev, __global uint *ew)
{
    const uint b = get_global_id(0);
    const uint g0 = b * B;
    if (g0 >= n) return;
    const uint g1 = min(g0 + B, n);
    const size_t e0 = (size_t)b * stride;
    pair_table t;
    clear(&t);
    size_t o = e0;
    for (uint g = g0; g < g1; ++g) {
        const uint cg = comp[g], fm = fmask[g];
        for (uint s = 0; s < k; ++s) {
            const size_t slot = (size_t)g * k + s;
            const uint j = nbr[slot];
            if (j == NONE) break;
            const uint cj = comp[j];
            const uint g_first = fm >> s & 1u;
            if (cj != cg)
                put(&t, cg, cj, g_first ? g : j, g_first ? j : g, as_uint(wgt[slot]), &o,
                    eu, ev, ew, bw, 1, order);
        }
    }
    flush(&t, &o, eu, ev, ew, bw, 1);
    counts[b] = (uint)(o - e0);
}

/* Every root g hooks onto the component across its lightest edge: link[g] = D << 1 | parity
 * of g relative to D (g << 1 for a root without edges); its edge goes to (flo, fhi) (input
 * indices). Resets the root's bw, blo, bhi for the next round. */
__kernel void hook(const uint n, __global const uint *roots, __global const uint *comp,
                   __global const uchar *par,
                   __global const uint *rank, __global const REAL *NX,
                   __global const REAL *NY, __global const REAL *NZ, __global uint *bw,
                   __global uint *blo, __global uint *bhi, __global uint *link,
                   __global uint *flo, __global uint *fhi)
{
    const uint i = get_global_id(0);
    if (i >= n) return;
    const uint g = roots[i];
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

/* hook for round 1 (every point a root): the other endpoint is own_j[g] when g's own list
 * holds the lightest edge, else found by rank. Resets bw, bhi and own_j (blo). */
__kernel void first_hook(const uint n, __global const uint *order, __global const uint *rank,
                         __global const REAL *NX, __global const REAL *NY,
                         __global const REAL *NZ, __global const uint *own_o,
                         __global uint *own_j, __global uint *bw, __global uint *bhi,
                         __global uint *link, __global uint *flo, __global uint *fhi)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    if (bw[g] == NONE) {
        link[g] = g << 1;
        return;
    }
    const uint og = order[g], ot = bhi[g];
    const uint v = ot == own_o[g] ? own_j[g] : rank[ot];
    const int g_lo = og < ot;
    const uint a = g_lo ? g : v, b = g_lo ? v : g;
    const uint pe = dot3((REAL3)(NX[a], NY[a], NZ[a]), (REAL3)(NX[b], NY[b], NZ[b])) < 0;
    link[g] = v << 1 | pe;
    flo[g] = g_lo ? og : ot; fhi[g] = g_lo ? ot : og;
    bw[g] = NONE; bhi[g] = NONE; own_j[g] = NONE;
}

/* Kernels of the roots of a round take them from roots[0 .. n) (all: 0 .. n - 1).
 *
 * Mutual hooks (C onto D and D onto C, through the same edge): the root with the smaller
 * input index stays a root. link -> link2; the edge of a root that stays one is dropped. */
__kernel void break_pairs(const uint n, __global const uint *roots, const uint all,
                          __global const uint *order,
                          __global const uint *link, __global uint *link2,
                          __global uint *flo)
{
    const uint i = get_global_id(0);
    if (i >= n) return;
    const uint g = all ? i : roots[i];
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
__kernel void resolve(const uint n, __global const uint *roots, const uint all,
                      __global const uint *A,
                      const uint chase, __global uint *B, volatile __global uint *unfinished)
{
    const uint i = get_global_id(0);
    if (i >= n) return;
    const uint g = all ? i : roots[i];
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
__kernel void jump(const uint n, __global const uint *roots, const uint all,
                   __global const uint *A,
                   __global uint *B, volatile __global uint *changed)
{
    const uint i = get_global_id(0);
    if (i >= n) return;
    const uint g = all ? i : roots[i];
    const uint L = A[g];
    const uint L2 = A[L >> 1];
    B[g] = (L2 & ~1u) | ((L ^ L2) & 1u);
    if (L2 >> 1 != L >> 1) lower(changed, 0);
}

/* The roots of the round (roots[0 .. n)) that are still roots, in order, into out: per block
 * of B entries a count (count_roots), a prefix sum (scan_blocks), the writes (write_roots).
 * all: the entries are 0 .. n - 1 (roots unused). */
__kernel void count_roots(const uint n, __global const uint *roots, const uint all,
                          const uint B, __global const uint *comp, __global uint *counts)
{
    const uint b = get_global_id(0);
    const uint i0 = b * B;
    if (i0 >= n) return;
    const uint i1 = min(i0 + B, n);
    uint c = 0;
    for (uint i = i0; i < i1; ++i) {
        const uint g = all ? i : roots[i];
        c += comp[g] == g;
    }
    counts[b] = c;
}

__kernel void write_roots(const uint n, __global const uint *roots, const uint all,
                          const uint B, __global const uint *comp,
                          __global const uint *offsets, __global uint *out)
{
    const uint b = get_global_id(0);
    const uint i0 = b * B;
    if (i0 >= n) return;
    const uint i1 = min(i0 + B, n);
    uint o = offsets[b];
    for (uint i = i0; i < i1; ++i) {
        const uint g = all ? i : roots[i];
        if (comp[g] == g) out[o++] = g;
    }
}

/* Exclusive prefix sum of counts[0 .. m) into offsets, the sum into total[0]. One work-item:
 * m is a few thousand blocks. */
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

/* Results in input order: the parity, (when labels) the root's input index (-1 for an
 * invalid normal) and (when edges) the forest edge by which a point's component hooked, at
 * the point's input index (NONE where none). */
__kernel void forest_out(const uint n, __global const uint *order, __global const REAL *NX,
                         __global const uint *comp, __global const uchar *par,
                         __global const uint *flo, __global const uint *fhi,
                         const uint labels, const uint edges, __global long *label,
                         __global uchar *parity, __global uint *elo, __global uint *ehi)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const uint i = order[g];
    const int ok = !isnan(NX[g]);
    if (labels) label[i] = ok ? (long)order[comp[g]] : -1;
    parity[i] = ok ? par[g] : 0;
    if (edges) {
        elo[i] = flo[g];
        ehi[i] = fhi[g];
    }
}

/* The forest's edges in input order of the point that hooked (elo[i] != NONE): per block
 * of B input indices a count, a prefix sum (scan_blocks), the (lo, hi) rows as longs. */
__kernel void count_edges(const uint n, const uint B, __global const uint *elo,
                          __global uint *counts)
{
    const uint b = get_global_id(0);
    const uint i0 = b * B;
    if (i0 >= n) return;
    const uint i1 = min(i0 + B, n);
    uint c = 0;
    for (uint i = i0; i < i1; ++i) c += elo[i] != NONE;
    counts[b] = c;
}

__kernel void write_edges(const uint n, const uint B, __global const uint *elo,
                          __global const uint *ehi, __global const uint *offsets,
                          __global long *edges)
{
    const uint b = get_global_id(0);
    const uint i0 = b * B;
    if (i0 >= n) return;
    const uint i1 = min(i0 + B, n);
    size_t o = offsets[b];
    for (uint i = i0; i < i1; ++i) {
        const uint lo = elo[i];
        if (lo == NONE) continue;
        edges[2 * o] = lo;
        edges[2 * o + 1] = ehi[i];
        ++o;
    }
}
