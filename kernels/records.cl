/* records.cl -- per-point data between the kernels' layouts and the host's arrays.
 *
 * split_records: the operator kernels write one record of RECORD_WIDTH REALs per point at
 * its input index (one cache line per point: a scattered store per output array would cost
 * a miss each); this splits the records into contiguous input-order arrays, one per field,
 * so the host gets ready columns without a strided pass over all records per field.
 * gather_sorted: input-order rows (user normals) to padded sorted SoA columns. */
#include "common.h"

/* Field layout of split_records, set by build options (clcurv/cloud.py:fetch_records):
 * NF real fields, field k = columns S<k> .. S<k> + W<k> - 1 of the record; COUNT_COL (uint
 * bits) and STATUS_COL (a small integer). */
#ifndef NF
#define NF 0
#endif
#define SPLIT(k) for (int c = 0; c < W##k; ++c) o##k[(size_t)j * W##k + c] = v[S##k + c];

#ifdef COUNT_COL
/* Records (input order, sequential) to contiguous per-field arrays: every read and write
 * is sequential. */
__kernel void split_records(__global const REAL *rec, const uint n, __global REAL *o0,
                            __global REAL *o1, __global REAL *o2, __global REAL *o3,
                            __global REAL *o4, __global REAL *o5, __global uint *count,
                            __global uchar *status)
{
    const uint j = get_global_id(0);
    if (j >= n) return;
    REAL v[RECORD_WIDTH];
    vstore16(vload16(j, rec), 0, v);
#if NF > 0
    SPLIT(0)
#endif
#if NF > 1
    SPLIT(1)
#endif
#if NF > 2
    SPLIT(2)
#endif
#if NF > 3
    SPLIT(3)
#endif
#if NF > 4
    SPLIT(4)
#endif
#if NF > 5
    SPLIT(5)
#endif
    count[j] = REAL_AS_UINT(v[COUNT_COL]);
    status[j] = (uchar)v[STATUS_COL];
}
#endif

/* Sorted SoA columns (padded: entries n .. n + PAD - 1 are 0) of input-order rows V (n, 3). */
__kernel void gather_sorted(__global const REAL *V, __global const uint *order, const uint n,
                            __global REAL *OX, __global REAL *OY, __global REAL *OZ)
{
    const uint s = get_global_id(0);
    if (s >= n + PAD) return;
    const REAL3 v = s < n ? vload3(order[s], V) : (REAL3)(0);
    OX[s] = v.x; OY[s] = v.y; OZ[s] = v.z;
}
