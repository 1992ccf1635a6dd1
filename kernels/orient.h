/* orient.h -- what the orientation graph (knn.cl) and its forest (forest.cl) share. */
#ifndef CLCURV_ORIENT_H
#define CLCURV_ORIENT_H
#include "common.h"

#define NONE 0xffffffffu
/* longest neighbour list (clcurv/orient/graph.py checks k against it: graph.KMAX) */
#define KMAX 32

/* a . b with its roundings spelled out (fma is exact then rounded once on every device), so
 * that no compiler's choice to contract a product and a sum changes a weight or a parity */
inline REAL dot3(REAL3 a, REAL3 b)
{
    return fma(a.z, b.z, fma(a.y, b.y, a.x * b.x));
}
#endif
