/* sgm_recurrence.h - SGM's penalty selection and recurrence: the one
 * statement of them that every SGM kernel uses (sgm.cl: sgm_rows,
 * sgm_columns, sgm_paired; sgm_wg.cl: sgm_wg_path).
 *
 * Along a path r, at pixel p and disparity level d:
 *
 *   C_r(p, d) = C(p, d) - m + min( C_r(p - r, d),
 *                                  m + P2,
 *                                  min(C_r(p - r, d - 1), C_r(p - r, d + 1)) + P1 )
 *   m = min_k C_r(p - r, k)
 *
 * (levels outside p - r's valid range read as +INFINITY; the first pixel of
 * a path has C_r = C).  P1 and P2 depend on how many of the two gradients
 * are large (>= tau_so, or NaN):
 *
 *   D1 = |I^L(p) - I^L(p - r)|,  D2 = |I^R(p - d) - I^R(p - d - r)|
 *   none large: *_small,  one: *_one,  both: *_both
 *
 * (mccnn_cl/stages/sgm.py, penalty_table, makes the three values of each).
 * The kernels choose in two steps, D1 once per pixel (SGM_BY_D1: the
 * penalty for a small D2 in a, for a large D2 in b), then D2 per level
 * (SGM_BY_D2).  Every kernel evaluates the recurrence with these functions,
 * in this order of operations, so they all give the same bits.
 */
#ifndef SGM_RECURRENCE_H
#define SGM_RECURRENCE_H

/* a gradient is large: scalar 1/0; vector lanes -1/0 (float16 / float8 lanes) */
#define SGM_LARGE(diff, tau) (!isless(fabs(diff), (tau)))
#define SGM_LARGE_T(diff, tau, FT, IT) (isless(fabs(diff), (FT)(tau)) == (IT)(0))
#define SGM_LARGE16(diff, tau) SGM_LARGE_T(diff, tau, float16, int16)
#define SGM_LARGE8(diff, tau) SGM_LARGE_T(diff, tau, float8, int8)

/* D1's step: a (D2 small) and b (D2 large) from the pixel's D1 flag */
#define SGM_BY_D1(small, one, both, big_l, a, b) \
    do {                                         \
        (a) = (big_l) ? (one) : (small);         \
        (b) = (big_l) ? (both) : (one);          \
    } while (0)
#define SGM_BY_D1_T(small, one, both, big_l, a, b, FT)         \
    do {                                                       \
        (a) = select((FT)(small), (FT)(one), (big_l));         \
        (b) = select((FT)(one), (FT)(both), (big_l));          \
    } while (0)
#define SGM_BY_D1_16(small, one, both, big_l, a, b) SGM_BY_D1_T(small, one, both, big_l, a, b, float16)
#define SGM_BY_D1_8(small, one, both, big_l, a, b) SGM_BY_D1_T(small, one, both, big_l, a, b, float8)
/* D2's step (vector lanes: big_r -1/0; any width) */
#define SGM_BY_D2_16(a, b, big_r) select((a), (b), (big_r))
#define SGM_BY_D2(a, b, big_r) ((big_r) ? (b) : (a))

/* fmin (OpenCL: y if y < x, else x; the other argument if one is NaN) with
 * one comparison instead of a NaN test and a comparison, where one argument
 * is known never to be NaN; the same value as fmin in every such case, ties
 * included.  fmin_aN: a is never NaN; fmin_bN: b is never NaN.
 *
 * The recurrence sgm_stepN: C_r(p, d) from the cost c = C(p, d), m, and
 * C_r(p - r, .) at d - 1 (lo), d and d + 1 (hi).  m is never NaN (a minimum
 * from +INFINITY through fmin, which drops NaN), so neither is m + P2:
 * fmin_b and fmin_a are fmin there; C_r(p - r, .) may be NaN (a NaN cost).
 * sgm_step_mp2N takes m + P2 instead of P2: where P2 is a select of two
 * values, the select of the two sums m + P2a, m + P2b (made once per pixel
 * or row) is the same value as m + select(P2a, P2b), one add fewer per
 * vector.  One text for float16 and float8 lanes (N = 16, 8), the scalar
 * sgm_step below in the same order of operations. */
#define SGM_VECTOR_FUNCTIONS(N)                                                                            \
    static inline __attribute__((always_inline)) float##N fmin_a##N(const float##N a, const float##N b)   \
    {                                                                                                      \
        return select(a, b, b < a);                                                                        \
    }                                                                                                      \
    static inline __attribute__((always_inline)) float##N fmin_b##N(const float##N a, const float##N b)   \
    {                                                                                                      \
        return select(a, b, !(a <= b));                                                                    \
    }                                                                                                      \
    static inline __attribute__((always_inline)) float##N sgm_step_mp2##N(                                \
        const float##N c, const float##N m, const float##N lo, const float##N d, const float##N hi,        \
        const float##N p1, const float##N mp2)                                                             \
    {                                                                                                      \
        const float##N best = fmin_a##N(fmin_b##N(d, mp2), fmin(lo, hi) + p1);                             \
        return c - m + best;                                                                               \
    }                                                                                                      \
    static inline __attribute__((always_inline)) float##N sgm_step##N(                                    \
        const float##N c, const float##N m, const float##N lo, const float##N d, const float##N hi,        \
        const float##N p1, const float##N p2)                                                              \
    {                                                                                                      \
        return sgm_step_mp2##N(c, m, lo, d, hi, p1, m + p2);                                               \
    }
SGM_VECTOR_FUNCTIONS(16)
SGM_VECTOR_FUNCTIONS(8)

static inline __attribute__((always_inline)) float sgm_step(
    const float c, const float m, const float lo, const float d, const float hi, const float p1, const float p2)
{
    const float best = fmin(fmin(d, m + p2), fmin(lo, hi) + p1);
    return c - m + best;
}

#endif
