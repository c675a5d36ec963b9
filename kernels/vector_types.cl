/*
 * vector_types.cl: explicit vector types for kernels that process VW consecutive
 * doubles per work item (build option -DVW=1|2|4|8|16, default 1).  PoCL does not
 * vectorise scalar kernels with inner loops; GPUs use VW = 1.
 *
 *   realv / longv / intv   double, long, int vectors of width VW (maskv = longv)
 *   VLOAD(o, p)            vector o of p (vloadVW), VSTORE(x, o, p) the store
 *   CONVERT_INTV(x)        convert_intVW;  CONVERT_REALV(x) convert_doubleVW
 *   CONVERT_V(type, x)     convert_<type>VW;  AS_LONGV(x) as_longVW
 *   ANY(c), SELECT(a, b, m), GREATER(a, b)   scalar/vector-agnostic any, select, isgreater
 *   CAT(a, b)              token pasting after expansion
 *
 * Include with #include "vector_types.cl" (the kernel directory is on the
 * include path of every program, see slicersim/opencl.py).
 */
#ifndef SLICERSIM_VECTOR_TYPES_CL
#define SLICERSIM_VECTOR_TYPES_CL

#if defined(cl_khr_fp64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifndef VW
#define VW 1
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

#if VW == 1
typedef double realv;
typedef long longv;
typedef int intv;
#define VLOAD(o, p) ((p)[o])
#define VSTORE(x, o, p) ((p)[o] = (x))
#define CONVERT_INTV convert_int
#elif VW == 2
typedef double2 realv;
typedef long2 longv;
typedef int2 intv;
#define VLOAD(o, p) vload2((o), (p))
#define VSTORE(x, o, p) vstore2((x), (o), (p))
#define CONVERT_INTV convert_int2
#elif VW == 4
typedef double4 realv;
typedef long4 longv;
typedef int4 intv;
#define VLOAD(o, p) vload4((o), (p))
#define VSTORE(x, o, p) vstore4((x), (o), (p))
#define CONVERT_INTV convert_int4
#elif VW == 8
typedef double8 realv;
typedef long8 longv;
typedef int8 intv;
#define VLOAD(o, p) vload8((o), (p))
#define VSTORE(x, o, p) vstore8((x), (o), (p))
#define CONVERT_INTV convert_int8
#elif VW == 16
typedef double16 realv;
typedef long16 longv;
typedef int16 intv;
#define VLOAD(o, p) vload16((o), (p))
#define VSTORE(x, o, p) vstore16((x), (o), (p))
#define CONVERT_INTV convert_int16
#else
#error "VW must be 1, 2, 4, 8 or 16"
#endif

typedef longv maskv;

#if VW == 1
#define AS_LONGV as_long
#define ANY(c) (c)
#define SELECT(a, b, m) ((m) ? (b) : (a))
#define GREATER(a, b) ((long)((a) > (b)))
#define CONVERT_REALV(x) ((double)(x))
#define CONVERT_V(type, x) ((type)(x))
#else
#define AS_LONGV CAT(as_long, VW)
#define ANY(c) any(c)
#define SELECT(a, b, m) select((a), (b), (m))
#define GREATER(a, b) isgreater((a), (b))
#define CONVERT_REALV(x) CAT(convert_double, VW)(x)
#define CONVERT_V(type, x) CAT(convert_, CAT(type, VW))(x)
#endif

#endif
