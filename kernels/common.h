/* common.h -- precision and vector-width macros shared by every clcurv kernel.
 *
 * Build options (set by clcurv/program.py, never by editing a kernel):
 *   -D REAL_IS_DOUBLE=0|1   scalar type REAL = float or double (double needs cl_khr_fp64)
 *   -D VW=2|4|8|16          width of the explicit vectors used in neighbour loops
 */
#ifndef CLCURV_COMMON_H
#define CLCURV_COMMON_H

#ifndef REAL_IS_DOUBLE
#define REAL_IS_DOUBLE 0
#endif
#ifndef VW
#define VW 8
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

#if REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define REAL double
#define IREAL long             /* integer type of a REAL comparison result */
#define REAL_EPS DBL_EPSILON
#define REAL_MAX DBL_MAX
#else
#define REAL float
#define IREAL int
#define REAL_EPS FLT_EPSILON
#define REAL_MAX FLT_MAX
#endif

#define REAL2 CAT(REAL, 2)
#define REAL3 CAT(REAL, 3)
#define REAL4 CAT(REAL, 4)
#define REALV CAT(REAL, VW)     /* VW lanes of REAL */
#define IREALV CAT(IREAL, VW)   /* VW lanes of comparison masks */
#define VLOADV CAT(vload, VW)

/* Per-point output records: RECORD_WIDTH REALs per point (the field layout is the kernel's,
 * mirrored in its host module), written with one vector store at the point's input index:
 * one cache line per point in float32, where a scattered store per output array costs a
 * cache miss each. records.cl:split_records turns them into per-field arrays. Integer
 * fields keep their bits (UINT_AS_REAL). */
#define RECORD_WIDTH 16
#define PAD 16                   /* zero padding of each per-point array (grid.py PAD) */
#define REAL16 CAT(REAL, 16)
#if REAL_IS_DOUBLE
#define UINT_AS_REAL(u) as_double((ulong)(u))
#define REAL_AS_UINT(x) ((uint)as_ulong(x))
#else
#define UINT_AS_REAL(u) as_float((uint)(u))
#define REAL_AS_UINT(x) as_uint(x)
#endif
#define STORE_RECORD(rec, j, out) vstore16((rec), (j), (out))

/* Per-point status codes (mirrored in clcurv/result.py). */
#define ST_OK 0
#define ST_TOO_FEW 1      /* fewer neighbours than the operator needs */
#define ST_DEGENERATE 2   /* covariance of rank < 2 (collinear or coincident points) */
#define ST_SINGULAR 3     /* a least-squares system could not be solved */

#endif
