/* lanes_records.h -- the records of a work-item's VW points from column vectors.
 *
 * A kernel that evaluates its outputs in the vector lanes (lane k: point g0 + k) holds them
 * as columns: col[c] the VW values of record column c (NaN already where a point's status
 * says so). REC_STORE_LANES(col, kn, g0, out, used) stores the records of the first kn
 * lanes, one REAL16 per point with REC_STORE at REC_INDEX(g0 + k): NaN but for the columns
 * of the constant mask used (bit c: column c), which are copied to a private array once
 * and set from it point by point. On the 1M-point features kernel (14 columns) on a 2-core
 * AVX2 CPU this took 86 ms against 89 for the features stored to private arrays one by one
 * and set in a record per point that branched on its status, and against 89.5 for the
 * records transposed from the columns in registers (two 8 x 8 shuffle transposes per 8
 * points). col must be an array of 16 REALV indexed by constants (it stays in registers).
 */
#ifndef CLCURV_LANES_RECORDS_H
#define CLCURV_LANES_RECORDS_H
#include "common.h"

/* the count column (uint bits, UINT_AS_REAL) of the lanes' counts cnt[VW] */
#if REAL_IS_DOUBLE
#define LANES_COUNT(cnt) CAT(as_, REALV)(CAT(convert_, CAT(ulong, VW))(CAT(vload, VW)(0, (cnt))))
#else
#define LANES_COUNT(cnt) CAT(as_, REALV)(CAT(vload, VW)(0, (cnt)))
#endif

/* rec's component c (a constant after unrolling: the switch folds) = v */
#define REC_SET(rec, c, v)                                                                \
    switch (c) {                                                                          \
    case 0: (rec).s0 = (v); break;  case 1: (rec).s1 = (v); break;                        \
    case 2: (rec).s2 = (v); break;  case 3: (rec).s3 = (v); break;                        \
    case 4: (rec).s4 = (v); break;  case 5: (rec).s5 = (v); break;                        \
    case 6: (rec).s6 = (v); break;  case 7: (rec).s7 = (v); break;                        \
    case 8: (rec).s8 = (v); break;  case 9: (rec).s9 = (v); break;                        \
    case 10: (rec).sa = (v); break; case 11: (rec).sb = (v); break;                       \
    case 12: (rec).sc = (v); break; case 13: (rec).sd = (v); break;                       \
    case 14: (rec).se = (v); break; default: (rec).sf = (v); break;                       \
    }

/* the columns col into t[16][VW] (REC_STORE_LANES' first step) */
#define REC_STAGE_LANES(col, t, used)                                                     \
    _Pragma("unroll") for (int c_ = 0; c_ < 16; ++c_)                                     \
        if (((used) >> c_) & 1) CAT(vstore, VW)((col)[c_], 0, (t)[c_]);
/* the record of lane k from the staged columns t, stored at j of out */
#define REC_EMIT(t, k, used, j, out)                                                      \
    {                                                                                     \
        REAL16 r_ = (REAL16)(NAN);                                                        \
        _Pragma("unroll") for (int c_ = 0; c_ < 16; ++c_)                                 \
            if (((used) >> c_) & 1) REC_SET(r_, c_, (t)[c_][k])                           \
        REC_STORE(r_, (j), out);                                                          \
    }
/* REC_HOST (CPU devices with cl_khr_fp64: clcurv/features.py): the records as rows of 16
 * doubles, stored at row j of the caller's float64 (N, 16) array itself (USE_HOST_PTR),
 * with no record buffer and no split. The columns are cast to double as vectors (the
 * split's casts, lane by lane), count (column cc, uint bits) and status (column cs, a small
 * integer) to the bits of an int64 and of its low byte, which the host reads through int64
 * and uint8 views; then each lane's row is one non-temporal store of two whole lines (the
 * array is 128-byte aligned). */
#if REAL_IS_DOUBLE
#define LANES_UINT_BITS(v) CAT(convert_uint, VW)(CAT(as_ulong, VW)(v))
#else
#define LANES_UINT_BITS(v) CAT(as_uint, VW)(v)
#endif
#define DOUBLEV CAT(double, VW)
#define REC_HOST_COLUMN(col, c, cc, cs)                                                   \
    ((c) == (cc) ? CAT(as_double, VW)(CAT(convert_ulong, VW)(LANES_UINT_BITS((col)[c])))  \
     : (c) == (cs) ? CAT(as_double, VW)(CAT(convert_ulong, VW)((col)[c]))                 \
     : CAT(convert_double, VW)((col)[c]))
/* the columns col into t[16][VW] of doubles (REC_EMIT_HOST's first step) */
#define REC_STAGE_HOST(col, t, used, cc, cs)                                              \
    _Pragma("unroll") for (int c_ = 0; c_ < 16; ++c_)                                     \
        if (((used) >> c_) & 1) CAT(vstore, VW)(REC_HOST_COLUMN(col, c_, cc, cs), 0, (t)[c_]);
#define REC_EMIT_HOST(t, k, used, j, out)                                                 \
    {                                                                                     \
        double16 r_ = (double16)(NAN);                                                    \
        _Pragma("unroll") for (int c_ = 0; c_ < 16; ++c_)                                 \
            if (((used) >> c_) & 1) REC_SET(r_, c_, (t)[c_][k])                           \
        REC_STORE_HOST(r_, (j), out);                                                     \
    }
#if defined(__has_builtin)
#if __has_builtin(__builtin_nontemporal_store)
#define REC_STORE_HOST(rec, j, out) \
    __builtin_nontemporal_store((rec), (__global double16 *)(out) + (j))
#endif
#endif
#ifndef REC_STORE_HOST
#define REC_STORE_HOST(rec, j, out) vstore16((rec), (j), (__global double *)(out))
#endif
#define REC_STORE_LANES(col, kn, g0, out, used)                                           \
    {                                                                                     \
        REAL t_[16][VW];                                                                  \
        REC_STAGE_LANES(col, t_, used)                                                    \
        for (uint k_ = 0; k_ < (kn); ++k_) REC_EMIT(t_, k_, used, REC_INDEX((g0) + k_), out) \
    }

#endif
