/* anchor.cl -- a reference ("anchor") normal per occupied cell, for the one-walk lambda0 of
 * pca.h (PCA_ANCHOR): the PCA normal of the cell's own points.
 *
 * One work-item per VW consecutive cells: each cell's points (or, for a cell of fewer than
 * ANCHOR_MIN_POINTS, those of its row of three cells along x) are summed in one pass, VW
 * points at a time, as offsets from the first of them, then the VW covariances are
 * decomposed at once by eig3_sym_v. Fewer than 3 points, or a covariance
 * of rank < 2, give the zero vector: the cell's points then take the second walk (pca.h).
 * The anchor only has to be near the balls' own normals; its sign is irrelevant.
 */
#include "common.h"
#include "neighbors.h"
#include "eig3.h"

#define VSTOREV CAT(vstore, VW)

/* fewest points of a cell whose anchor is computed from its own points; a cell with fewer
 * uses the points of its row of three cells along x (ranges[ROW_INDEX(c, 4)], neighbors.h) */
#define ANCHOR_MIN_POINTS 6u

__kernel void cell_normals(__global const REAL *X, __global const REAL *Y,
                           __global const REAL *Z, __global const uint *cell_start,
                           __global const uint *cell_of, __global const uint2 *ranges,
                           const uint n,
                           const uint ncells, __global REAL *CN)
{
    const uint c0 = get_global_id(0) * VW;
    if (c0 >= ncells) return;
    REAL c[6][VW];
    uint cnt[VW];
    for (uint k = 0; k < VW; ++k) {
        const uint cell = min(c0 + k, ncells - 1);
        uint a = cell_start[cell], b = cell_start[cell + 1];
        if (b - a < ANCHOR_MIN_POINTS) {            /* few points: the row of 3 cells */
            const uint2 row = ranges[ROW_INDEX(cell, 4)];
            a = row.x; b = row.y;
        }
        /* the x copy of the cell's rows (neighbors.h): continuous over the row of 3 cells */
        __global const REAL *XA = x_rows(X, cell_of[cell_start[cell]], n);
        /* one pass, VW points at a time (the arrays are padded: neighbors.h), offsets from
         * the first point: small numbers, and the anchor needs only its direction to
         * ~1e-2 (pca.h: ANCHOR_SIN2), which the one-pass covariance holds by far */
        const REAL3 o = (REAL3)(XA[a], Y[a], Z[a]);
        REALV sx = 0, sy = 0, sz = 0, sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
        for (uint i = a; i < b; i += VW) {
            const IREALV live = LANES < (IREALV)((IREAL)(b - i));
            /* the offsets zeroed past the range (3 selects), then plain sums (pca.h) */
            const REALV dx = select((REALV)0, VLOADV(0, XA + i) - o.x, live);
            const REALV dy = select((REALV)0, VLOADV(0, Y + i) - o.y, live);
            const REALV dz = select((REALV)0, VLOADV(0, Z + i) - o.z, live);
            sx += dx; sy += dy; sz += dz;
            sxx += dx * dx; sxy += dx * dy; sxz += dx * dz;          /* fused: pca.h */
            syy += dy * dy; syz += dy * dz; szz += dz * dz;
        }
        const REAL inv = (REAL)1 / (REAL)max(b - a, 1u);
        const REAL3 m = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * inv;
        c[0][k] = hsum(sxx) * inv - m.x * m.x; c[1][k] = hsum(sxy) * inv - m.x * m.y;
        c[2][k] = hsum(sxz) * inv - m.x * m.z; c[3][k] = hsum(syy) * inv - m.y * m.y;
        c[4][k] = hsum(syz) * inv - m.y * m.z; c[5][k] = hsum(szz) * inv - m.z * m.z;
        cnt[k] = b - a;
    }
    REALV w0, w1, w2;
    eig3_v3_v e0, e1, e2;
    eig3_sym_v(VLOADV(0, c[0]), VLOADV(0, c[1]), VLOADV(0, c[2]), VLOADV(0, c[3]),
               VLOADV(0, c[4]), VLOADV(0, c[5]), &w0, &w1, &w2, &e0, &e1, &e2);
    REAL l1[VW], l2[VW], nx[VW], ny[VW], nz[VW];
    VSTOREV(w1, 0, l1); VSTOREV(w2, 0, l2);
    VSTOREV(e0.x, 0, nx); VSTOREV(e0.y, 0, ny); VSTOREV(e0.z, 0, nz);
    for (uint k = 0; k < VW && c0 + k < ncells; ++k) {
        const int ok = cnt[k] >= 3 && l2[k] > 0 && l1[k] > (REAL)1e-3 * l2[k];
        const REAL3 v = ok ? (REAL3)(nx[k], ny[k], nz[k]) : (REAL3)(0);
        vstore3(v, c0 + k, CN);
    }
}
