/* common.h -- precision and vector-width macros shared by every clcurv kernel.
 *
 * Build options (set by clcurv/runtime/program.py, never by editing a kernel):
 *   -D REAL_IS_DOUBLE=0|1   scalar type REAL = float or double (double needs cl_khr_fp64)
 *   -D VW=2|4|8|16          width of the explicit vectors used in neighbour loops
 * and the host's constants, defined once in clcurv/_shared/constants.py (kernel_defines): PAD,
 * RECORD_WIDTH, CELL_BITS, CELL_MASK, the status codes ST_* and the minimum neighbour
 * counts MIN_COUNT_PCA, MIN_COUNT_MLS2. No kernel defines or defaults any of them.
 */
#ifndef CLCURV_COMMON_H
#define CLCURV_COMMON_H

#if !defined(REAL_IS_DOUBLE) || !defined(VW) || !defined(PAD) || !defined(RECORD_WIDTH) \
    || !defined(CELL_BITS) || !defined(CELL_MASK) || !defined(ST_OK) || !defined(ST_TOO_FEW) \
    || !defined(ST_DEGENERATE) || !defined(ST_SINGULAR) || !defined(MIN_COUNT_PCA) \
    || !defined(MIN_COUNT_MLS2)
#error "clcurv kernels take their constants from the host: build them with clcurv.runtime.program.build"
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

#if REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define REAL double
#define IREAL long             /* integer type of a REAL comparison result */
#else
#define REAL float
#define IREAL int
#endif

#define REAL2 CAT(REAL, 2)
#define REAL3 CAT(REAL, 3)
#define REAL4 CAT(REAL, 4)
#define REALV CAT(REAL, VW)     /* VW lanes of REAL */
#define IREALV CAT(IREAL, VW)   /* VW lanes of comparison masks */
#define VLOADV CAT(vload, VW)
/* twice VW lanes (VW <= 8): two batches of VW points at once (eig3.h: eig3_sym_g_w) */
#if VW == 2
#define VW2 4
#elif VW == 4
#define VW2 8
#elif VW == 8
#define VW2 16
#endif
#ifdef VW2
#define REALW CAT(REAL, VW2)
#define IREALW CAT(IREAL, VW2)
#endif

/* Per-point output records: RECORD_WIDTH REALs per point, written with one vector store at
 * the point's input index (or its place in a chunk, REC_INDEX): one cache line per point in
 * float32, where a scattered store per
 * output array costs a cache miss each. records.cl:split_records turns them into per-field
 * arrays. The columns are the operator's (clcurv/ops/registry.py), given as -D COL_<FIELD>
 * options holding the field's REAL16 component selector (COL_NORMALS=s012, COL_COUNT=sa):
 * a record is a REAL16 value written by swizzles, which stays in registers (a private
 * array indexed by column numbers cost 10-30% of the kernels under PoCL). Integer fields
 * keep their bits (UINT_AS_REAL).
 *   REAL16 rec = (REAL16)(NAN); rec.COL_NORMALS = v0; ...; REC_STORE(rec, j, out); */
#if REAL_IS_DOUBLE
#define UINT_AS_REAL(u) as_double((ulong)(u))
#define REAL_AS_UINT(x) ((uint)as_ulong(x))
#else
#define UINT_AS_REAL(u) as_float((uint)(u))
#define REAL_AS_UINT(x) as_uint(x)
#endif
#if RECORD_WIDTH != 16
#error "records are REAL16 values"
#endif
#define REAL16 CAT(REAL, 16)
/* count and status, the two columns every record has */
#define REC_COUNT_STATUS(rec, count, status) \
    { (rec).COL_COUNT = UINT_AS_REAL(count); (rec).COL_STATUS = (REAL)(status); }
/* Records land at input indices, i.e. scattered: a store that misses the cache. Where the
 * compiler has it (clang, as PoCL's), a non-temporal store of the whole record: one write of
 * a full line that needs no read of it first (vstore16 became three partial stores, each
 * waiting for its line; the moments kernel spent ~10% of its time on them). The record
 * buffers are aligned to their vector size (OpenCL: CL_DEVICE_MEM_BASE_ADDR_ALIGN >= the
 * largest type, REAL16 records at multiples of it). */
#if defined(__has_builtin)
#if __has_builtin(__builtin_nontemporal_store)
#define REC_STORE(rec, j, out) \
    __builtin_nontemporal_store((rec), (__global REAL16 *)(out) + (j))
#endif
#endif
#ifndef REC_STORE
#define REC_STORE(rec, j, out) vstore16((rec), (j), (out))
#endif
/* Where the record of ball b of the point at x in block blk lies when the records of nb
 * balls share one buffer in blocks of REC_BLOCK points, each block ball 0's REC_BLOCK
 * records, then ball 1's, ... (features.cl's REC_BALLS, records.cl's split with NB) */
#define REC_IN_BLOCKS(blk, x, b, nb) \
    ((size_t)(blk) * (REC_BLOCK * (nb)) + (size_t)(b) * REC_BLOCK + (x))

/* The count of a ball's points with uniform weights (pca.h and covariances.cl): acc, a
 * REALV that starts at 0, holds in its bits one integer per lane (as_IREALV), and each
 * chunk subtracts its mask m (lanes all ones, i.e. -1, or zero): one integer operation.
 * The float form acc += m ? 1 : 0 took two (an and with the constant 1.0, an add) and the
 * constant a register, in the loop that bounds the multi-radius walk (features.cl's
 * flush: 15 -> 13 vector operations a chunk and ball under PoCL 3.1 on AVX2, the 1M-point
 * three-radius kernel ~5 ms faster). acc's bits are integers, never read as floats: only
 * COUNT_TOTAL reads them, as the sum of the lanes (exact, counts < 2^24). */
#define MASKED_COUNT(acc, m) \
    acc = CAT(as_, REALV)(CAT(as_, IREALV)(acc) - (m));
#define COUNT_TOTAL(acc) ((REAL)hsum_i(CAT(as_, IREALV)(acc)))

/* The arguments of every operator kernel, in the order clcurv/ops/driver.py passes them: the
 * sorted coordinates (neighbors.h), the sorted reference normals NX, NY, NZ (unused by the
 * moments), the density weights W (read when DENSITY), the cells' anchor normals CN
 * (anchor.cl; read when REFINE_L0, pca.h), the grid, order (sorted -> input
 * index), the cloud's size n, the ball (r^2, cell), par = (r, 1 / h^2, 0, 0), the sorted
 * points [first, stop) of this launch, and the records: with chunk = 0 (the whole cloud)
 * the record of sorted point g goes to its input index order[g], with chunk = 1 to g - first
 * (a chunk-sized buffer that the host scatters by order: clcurv/ops/driver.py). */
#define OPERATOR_ARGS                                                                  \
    __global const REAL *X, __global const REAL *Y, __global const REAL *Z,            \
    __global const REAL *NX, __global const REAL *NY, __global const REAL *NZ,         \
    __global const REAL *W, __global const REAL *CN, __global const uint *cell_of,     \
    __global const uint2 *ranges,                                                      \
    __global const uint *order, const uint n, const REAL2 ball, const REAL4 par,       \
    const uint first, const uint stop, const uint chunk, __global REAL *out
/* The record index of sorted point g in an operator kernel (see OPERATOR_ARGS). */
#define REC_INDEX(g) (chunk ? (g) - first : order[(g)])

#endif
