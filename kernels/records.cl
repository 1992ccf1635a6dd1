/* records.cl -- split_records: the operator kernels write one record of RECORD_WIDTH REALs
 * per point at its input index, or at its place in a chunk of sorted points (one cache line
 * per point: a scattered store per output array would cost a miss each); this splits the
 * records into contiguous arrays in the same order, one per field, so the host gets ready
 * columns (or scatters a chunk's) without a strided pass over all records per field.
 * With SPLIT_HOST (a CPU device with cl_khr_fp64, clcurv/grid/cloud.py:place_records) the
 * arrays are the caller's float64 / int64 host arrays themselves (USE_HOST_PTR): the cast
 * happens here, in the same pass, instead of in a second pass on the host. */
#include "common.h"

/* Field layout, set by build options (clcurv/grid/cloud.py:split_records): NF real fields,
 * field k = columns S<k> .. S<k> + W<k> - 1 of the record; COL_COUNT (uint bits) and
 * COL_STATUS (a small integer), as REAL16 selectors (common.h). */
#if !defined(NF) || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "records.cl needs NF, COL_COUNT and COL_STATUS (clcurv/grid/cloud.py:split_records)"
#endif
/* With NB: ball REC_BALL's records among those of NB balls in one buffer, in blocks
 * (common.h: REC_IN_BLOCKS; features.cl's REC_BALLS) */
#if defined(SPLIT_HOST) && SPLIT_HOST
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define OUT_REAL double
#define OUT_COUNT long
#else
#define OUT_REAL REAL
#define OUT_COUNT uint
#endif
#define SPLIT(k) \
    for (int c = 0; c < W##k; ++c) o##k[(size_t)j * W##k + c] = (OUT_REAL)v[S##k + c];

/* Record r (of point j) into field k's array o<k>, count and status at j. */
inline void split_one(const REAL16 r, const uint j, __global OUT_REAL *o0,
                      __global OUT_REAL *o1, __global OUT_REAL *o2, __global OUT_REAL *o3,
                      __global OUT_REAL *o4, __global OUT_REAL *o5, __global OUT_COUNT *count,
                      __global uchar *status)
{
    REAL v[RECORD_WIDTH];
    vstore16(r, 0, v);
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
    count[j] = (OUT_COUNT)REAL_AS_UINT(r.COL_COUNT);
    status[j] = (uchar)r.COL_STATUS;
}

/* The first n records to contiguous per-field arrays in the same order: every read and
 * write is sequential. */
__kernel void split_records(__global const REAL *rec, const uint n,
                            __global OUT_REAL *o0, __global OUT_REAL *o1,
                            __global OUT_REAL *o2, __global OUT_REAL *o3,
                            __global OUT_REAL *o4, __global OUT_REAL *o5,
                            __global OUT_COUNT *count, __global uchar *status)
{
#ifdef NB
    /* work-items (x, block): x + block REC_BLOCK, x unit-stride in the records too */
    const uint x = get_global_id(0), blk = get_global_id(1);
    const uint j = blk * REC_BLOCK + x;
    if (j >= n || x >= REC_BLOCK) return;
    split_one(vload16(REC_IN_BLOCKS(blk, x, REC_BALL, NB), rec), j, o0, o1, o2, o3, o4, o5,
              count, status);
#else
    const uint j = get_global_id(0);
    if (j >= n) return;
    split_one(vload16(j, rec), j, o0, o1, o2, o3, o4, o5, count, status);
#endif
}
