/* vector.h - RN-wide float vectors for the network kernels.
 *
 * Include after RN (1, 2, 4, 8 or 16) is defined: VT is the vector type,
 * VLOAD(p) / VSTORE(v, p) move RN consecutive floats from / to p (any
 * alignment of a float).  RN == 1 falls back to plain scalars.
 */
#ifndef MCCNN_VECTOR_H
#define MCCNN_VECTOR_H

#ifndef RN
#error "RN (vector width: 1, 2, 4, 8 or 16) must be defined before including vector.h"
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#if RN == 1
#define VT float
#define VLOAD(p) (*(p))
#define VSTORE(v, p) (*(p) = (v))
#else
#define VT CAT(float, RN)
#define VLOAD(p) CAT(vload, RN)(0, (p))
#define VSTORE(v, p) CAT(vstore, RN)((v), 0, (p))
#endif

#endif /* MCCNN_VECTOR_H */
