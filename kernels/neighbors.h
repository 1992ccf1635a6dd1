/* neighbors.h -- the fixed-order walk over the candidates of one query point.
 *
 * The sorted points of the 27 cells around the query's cell form 9 contiguous index
 * ranges (one per (dz, dy) row of three cells, computed by grid.cl:cell_ranges). The walk
 * visits the ranges in order and each range VW points at a time; the arrays are padded
 * so a vector load may read past the end. Lanes past the range end or outside the open
 * ball |q - p| < r are masked out. The order is fixed, so results are bit-reproducible.
 *
 *   NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
 *       ... body using the chunk [i, i + VW) clipped to end ...
 *   NEIGHBOR_CHUNKS_END
 */
#ifndef CLCURV_NEIGHBORS_H
#define CLCURV_NEIGHBORS_H
#include "common.h"

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

#define NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)                      \
    for (int nb_row = 0; nb_row < 9; ++nb_row) {                          \
        const uint2 nb_se = (ranges)[(size_t)(cell) * 9 + nb_row];        \
        const uint end = nb_se.y;                                         \
        for (uint i = nb_se.x; i < end; i += VW) {
#define NEIGHBOR_CHUNKS_END }}

/* Offsets q - p of the chunk starting at i and the mask of lanes that are neighbours. */
inline IREALV chunk_offsets(__global const REAL *X, __global const REAL *Y,
                            __global const REAL *Z, uint i, uint end, REAL3 p, REAL r2,
                            REALV *dx, REALV *dy, REALV *dz)
{
    *dx = VLOADV(0, X + i) - p.x;
    *dy = VLOADV(0, Y + i) - p.y;
    *dz = VLOADV(0, Z + i) - p.z;
    const REALV d2 = (*dx) * (*dx) + (*dy) * (*dy) + (*dz) * (*dz);
    const IREALV live = LANES < (IREALV)((IREAL)(end - i));
    return live & isless(d2, (REALV)r2);
}

/* Sum of the lanes in a fixed order (pairwise), so the result is reproducible. */
inline REAL hsum(REALV v)
{
#if VW == 16
    CAT(REAL, 8) a = v.lo + v.hi;
    CAT(REAL, 4) b = a.lo + a.hi;
#elif VW == 8
    CAT(REAL, 4) b = v.lo + v.hi;
#elif VW == 4
    CAT(REAL, 4) b = v;
#endif
#if VW >= 4
    CAT(REAL, 2) c = b.lo + b.hi;
    return c.x + c.y;
#else
    return v.x + v.y;
#endif
}

#endif
