/* neighbors.h -- the fixed-order walk over the candidates of one query point.
 *
 * The sorted points of the 27 cells around the query's cell form 9 contiguous index
 * ranges, one per row j of three cells (cx - 1 .. cx + 1, cy + dy, cz + dz) with
 * (dz, dy) = (j / 3 - 1, j % 3 - 1) (grid.cl:cell_ranges; an empty row is (0, 0)). The walk
 * visits the rows in order (with ROW_PRUNE, skipping those whose slab lies beyond the
 * radius in y and z: row_gap2, and the whole chunks of a row's first or last cell beyond it
 * in x: row_first, row_stop) and each range VW points at a time; the arrays are padded so a
 * vector load may read past the end. Lanes past the range end or outside the open ball
 * |q - p| < r are masked out. The order is fixed, so results are bit-reproducible.
 *
 * Coordinates are stored relative to their cell (grid.py), so offsets q - p are small
 * numbers known to the device precision whatever the cloud's extent or offset: y and z
 * from the corner of the point's cell, so that in row j q_y - p_y = Y - (p_y - dy c)
 * (likewise z); x three times, from the corner of the point's block of three cells along
 * x in the alignments a = 0, 1, 2 (blocks starting at cell indices = a mod 3). The rows of
 * a point in cell cx lie in one block of alignment (cx - 1) mod 3, kept in the top bits of
 * cell_of: with that copy of x, q_x - p_x = X - p_x exactly as well.
 *
 *   const uint co = cell_of[g];
 *   __global const REAL *XA = x_rows(X, co, n);         the point's x copy
 *   p = (XA[g], Y[g], Z[g]); cell = co & CELL_MASK;
 *   NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
 *       ... chunk_offsets(XA, Y, Z, i, end, pr, ball, &dx, &dy, &dz) for [i, i + VW) ...
 *   NEIGHBOR_CHUNKS_END
 *
 * with REAL2 ball = (r^2, c).
 */
#ifndef CLCURV_NEIGHBORS_H
#define CLCURV_NEIGHBORS_H
#include "common.h"

/* CELL_BITS, CELL_MASK (host constants): cell_of = alignment << CELL_BITS | cell id */

/* The copy of x that sorted point g's rows use (co = cell_of[g]). */
inline __global const REAL *x_rows(__global const REAL *X, uint co, uint n)
{
    return X + (size_t)(co >> CELL_BITS) * (n + PAD);
}

#if VW == 2
#define LANES ((IREALV)(0, 1))
#elif VW == 4
#define LANES ((IREALV)(0, 1, 2, 3))
#elif VW == 8
#define LANES ((IREALV)(0, 1, 2, 3, 4, 5, 6, 7))
#elif VW == 16
#define LANES ((IREALV)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#else
#error "VW must be 2, 4, 8 or 16"
#endif

/* ROW_PRUNE (0|1, the host's choice: clcurv/ops/driver.py:row_prune): skip the rows of the
 * block farther than the ball's radius in y and z (the same sums as walking all 9:
 * tests/test_row_pruning.py). Worth it for a radius well below the cell; at r = cell only
 * corner rows can be skipped, rarely, and the test costs more than it saves. */
#ifndef ROW_PRUNE
#define ROW_PRUNE 0
#endif
#if REAL_IS_DOUBLE
#define ROW_SLACK (4 * DBL_EPSILON)
#else
#define ROW_SLACK (4 * FLT_EPSILON)
#endif
/* The squared distance from p (cell-relative y, z) to the slab of row (nb_y, nb_z) in y
 * and z, less a slack of a few ulps of the cell: no lane of a row farther than r can pass
 * chunk_offsets' test, so skipping such a row changes no sum (bit for bit). */
inline REAL row_gap2(REAL3 p, REAL2 ball, int nb_y, int nb_z)
{
    const REAL s = ROW_SLACK * ball.y;
    const REAL ey = nb_y == 1 ? (REAL)0 : fmax((nb_y == 0 ? p.y : ball.y - p.y) - s, (REAL)0);
    const REAL ez = nb_z == 1 ? (REAL)0 : fmax((nb_z == 0 ? p.z : ball.y - p.z) - s, (REAL)0);
    return ey * ey + ez * ez;
}

/* Where the rows of cell c and their middle cells lie in the cloud's ranges (grid.cl): a
 * header (ncells, middles), the 9 rows of every cell, then (when middles) the 9 middles of
 * every cell */
#define ROW_INDEX(c, j) (1 + (size_t)(c) * 9 + (j))
#define MIDDLE_AT(ncells, c, j) (1 + (size_t)(ncells) * 9 + (size_t)(c) * 9 + (j))
#define MIDDLE_INDEX(ranges, c, j) MIDDLE_AT((ranges)[0].x, c, j)

/* The first index of the walk of a row (its points [r.x, r.y), its middle cell's [m.x,
 * m.y); without middles m = r, which trims nothing): r.x, or with ROW_PRUNE, when the
 * row's first cell lies beyond the ball (gap2: its slab's squared distance), r.x plus the
 * whole chunks of VW points before the middle cell (their lanes all lie in that first
 * cell, beyond the ball: skipping them changes no sum, and the chunks that follow keep
 * their lanes); and the index the walk stops at: r.y, the middle cell's end when the last
 * cell lies beyond the ball, r.x for a row beyond it (all of whose lanes would fail the
 * ball test as well). */
inline uint row_first(uint2 r, uint2 m, REAL gap2, REAL r2)
{
    return ROW_PRUNE && !(gap2 < r2) ? r.x + (m.x - r.x) / VW * VW : r.x;
}

inline uint row_stop(uint2 r, uint2 m, REAL gyz, REAL gap2, REAL r2)
{
    return !ROW_PRUNE ? r.y : !(gyz < r2) ? r.x : gap2 < r2 ? r.y : m.y;
}

/* The squared distances from p (x relative to its row's 3-cell block, its own cell the
 * middle one) to the slabs of the cells before and after its own along x, less the slack
 * of row_gap2. */
inline REAL2 x_gaps2(REAL3 p, REAL2 ball)
{
    const REAL s = ROW_SLACK * ball.y;
    const REAL2 e = fmax((REAL2)(p.x - ball.y - s, 2 * ball.y - p.x - s), (REAL2)0);
    return e * e;
}

#define NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)         \
    for (int nb_z = 0; nb_z < 3; ++nb_z)                                  \
    for (int nb_y = 0; nb_y < 3; ++nb_y) {                                \
        const uint2 nb_r = (ranges)[ROW_INDEX(cell, nb_z * 3 + nb_y)];    \
        const uint2 nb_m = ROW_PRUNE && (ranges)[0].y                     \
                           ? (ranges)[MIDDLE_INDEX(ranges, cell, nb_z * 3 + nb_y)] : nb_r; \
        const REAL nb_gyz = ROW_PRUNE ? row_gap2(p, ball, nb_y, nb_z) : (REAL)0; \
        const REAL2 nb_gx = ROW_PRUNE ? x_gaps2(p, ball) : (REAL2)(0);     \
        const uint end = row_stop(nb_r, nb_m, nb_gyz, nb_gyz + nb_gx.y, (ball).x); \
        const REAL3 pr = (REAL3)((p).x, (p).y + (REAL)(1 - nb_y) * (ball).y, \
                                 (p).z + (REAL)(1 - nb_z) * (ball).y);    \
        for (uint i = row_first(nb_r, nb_m, nb_gyz + nb_gx.x, (ball).x); i < end; i += VW) {
#define NEIGHBOR_CHUNKS_END }}

/* |q - p|^2 of a chunk's offsets: the one expression of every ball test (chunk_offsets,
 * features.cl's balls, knn_radius.cl), so that a lane's membership, to the last bit, does
 * not depend on which kernel asks. */
inline REALV offsets_d2(REALV dx, REALV dy, REALV dz)
{
    return dx * dx + dy * dy + dz * dz;
}

/* Offsets q - p of the chunk starting at i (pr: the query point as seen from the chunk's
 * row, see the top), their |q - p|^2 in d2, and the mask of lanes that are neighbours. A
 * caller that tests other balls on the same chunk (features.cl) tests this d2, the very
 * value a single-ball call compares, without computing it again. */
inline IREALV chunk_offsets_d2(__global const REAL *X, __global const REAL *Y,
                               __global const REAL *Z, uint i, uint end, REAL3 pr, REAL2 ball,
                               REALV *dx, REALV *dy, REALV *dz, REALV *d2)
{
    *dx = VLOADV(0, X + i) - pr.x;
    *dy = VLOADV(0, Y + i) - pr.y;
    *dz = VLOADV(0, Z + i) - pr.z;
    *d2 = offsets_d2(*dx, *dy, *dz);
    const IREALV live = LANES < (IREALV)((IREAL)(end - i));
    return live & isless(*d2, (REALV)ball.x);
}
inline IREALV chunk_offsets(__global const REAL *X, __global const REAL *Y,
                            __global const REAL *Z, uint i, uint end, REAL3 pr, REAL2 ball,
                            REALV *dx, REALV *dy, REALV *dz)
{
    REALV d2;
    return chunk_offsets_d2(X, Y, Z, i, end, pr, ball, dx, dy, dz, &d2);
}

/* LANE_REDUCTION(name, T, F) defines  inline T name(T<VW> v): the VW lanes of v combined
 * by the binary F, pairwise (low half with high half, halving), a fixed order: sums are
 * reproducible. One definition for every lane reduction of the kernels (sums, OR, minima). */
#if VW == 16
#define LANE_REDUCTION(name, T, F)                                                 \
    inline T name(CAT(T, 16) v)                                                    \
    {                                                                              \
        const CAT(T, 8) a = F(v.lo, v.hi);                                         \
        const CAT(T, 4) b = F(a.lo, a.hi);                                         \
        const CAT(T, 2) c = F(b.lo, b.hi);                                         \
        return F(c.x, c.y);                                                        \
    }
#elif VW == 8
#define LANE_REDUCTION(name, T, F)                                                 \
    inline T name(CAT(T, 8) v)                                                     \
    {                                                                              \
        const CAT(T, 4) b = F(v.lo, v.hi);                                         \
        const CAT(T, 2) c = F(b.lo, b.hi);                                         \
        return F(c.x, c.y);                                                        \
    }
#elif VW == 4
#define LANE_REDUCTION(name, T, F)                                                 \
    inline T name(CAT(T, 4) v)                                                     \
    {                                                                              \
        const CAT(T, 2) c = F(v.lo, v.hi);                                         \
        return F(c.x, c.y);                                                        \
    }
#else
#define LANE_REDUCTION(name, T, F)                                                 \
    inline T name(CAT(T, 2) v) { return F(v.x, v.y); }
#endif
#define LANE_ADD(a, b) ((a) + (b))
#define LANE_OR(a, b) ((a) | (b))

/* Sum of the lanes in a fixed order (pairwise), so the result is reproducible. */
LANE_REDUCTION(hsum, REAL, LANE_ADD)

/* Sum of the integer lanes (the counts of MASKED_COUNT, common.h) */
LANE_REDUCTION(hsum_i, IREAL, LANE_ADD)

/* Is any lane of a mask set? The lanes narrowed to bytes (a mask lane is 0 or -1, so its
 * byte is too) and read as one integer: a compiler sees the sign bits of a comparison and
 * tests them together (PoCL 3.1 on AVX2: two packs and vpmovmskb, or vmovmskps), where an
 * OR tree of the lanes took five shuffles and ORs (the multi-radius features walk, which
 * tests every chunk, 2-5 ms faster at 1M points) and PoCL 3.1's any() made the second
 * pass of knn_graph about twice as slow. (clang's __builtin_reduce_or compiles to one
 * vptest, but Oclgrind does not implement it.) */
inline int any_lane(IREALV m)
{
#if VW == 16
    const ulong2 u = as_ulong2(convert_char16(m));
    return (u.x | u.y) != 0;
#elif VW == 8
    return as_ulong(convert_char8(m)) != 0;
#elif VW == 4
    return as_uint(convert_char4(m)) != 0;
#else
    return as_ushort(convert_char2(m)) != 0;
#endif
}

#endif
