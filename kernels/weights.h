/* weights.h -- per-neighbour weights of a chunk, set by build options:
 *   DENSITY  (0|1)  w(q) = 1 / #N_r(q), read from W (sorted order, padded)
 *   GAUSSIAN (0|1)  w *= exp(-|q - p|^2 / h^2), ih2 = 1 / h^2
 * Lanes outside the ball (mask m false) get weight 0. */
#ifndef CLCURV_WEIGHTS_H
#define CLCURV_WEIGHTS_H
#include "common.h"
#if !defined(DENSITY) || !defined(GAUSSIAN)
#error "weights.h needs DENSITY and GAUSSIAN (clcurv/ops/driver.py)"
#endif

inline REALV chunk_weights(__global const REAL *W, uint i, REALV dx, REALV dy, REALV dz,
                           IREALV m, REAL ih2)
{
#if DENSITY
    REALV w = VLOADV(0, W + i);
#else
    REALV w = (REALV)1;
#endif
#if GAUSSIAN
    w *= exp(-(dx * dx + dy * dy + dz * dz) * ih2);
#endif
    return select((REALV)0, w, m);
}

/* With uniform weights (w = the mask as 0/1) the sums of pca.h take the offsets zeroed
 * outside the ball instead of products w x (PCA_ACCUMULATE: 3 selects per chunk, then the
 * second moments as multiply-adds: the moments kernel of 1M points took 74 ms against 94
 * with a masked add per sum on the EPYC). */
#endif
