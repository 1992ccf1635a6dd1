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
#define REC_STORE_LANES(col, kn, g0, out, used)                                           \
    {                                                                                     \
        REAL t_[16][VW];                                                                  \
        REC_STAGE_LANES(col, t_, used)                                                    \
        for (uint k_ = 0; k_ < (kn); ++k_) REC_EMIT(t_, k_, used, REC_INDEX((g0) + k_), out) \
    }

#endif
