/*
 * vector_types.cl: explicit vector types for kernels that process VW consecutive
 * reals per work item (build option -DVW=1|2|4|8|16, default 1).  PoCL does not
 * vectorise scalar kernels with inner loops; GPUs use VW = 1.
 *
 * Precision: double by default; -DSINGLE (with -cl-single-precision-constant, so
 * that literals are float too: slicersim.backends.opencl.precision_options) makes
 * real = float, and longv the 32-bit integer of the same width (the bit tricks
 * that read a real's bits as an integer keep working).  A kernel file written in
 * real / realv compiles in both; kernels that stay double use double explicitly.
 *
 *   real, real2            the scalar floating type (double, or float with -DSINGLE), its pair
 *   realv / longv / intv   real, same-width integer, int vectors of width VW (maskv = longv)
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

#ifdef SINGLE
typedef float real;
typedef float2 real2;
#define REAL_NAME float
#define LONG_NAME int
#else
typedef double real;
typedef double2 real2;
#define REAL_NAME double
#define LONG_NAME long
#endif

#if VW == 1
typedef real realv;
typedef LONG_NAME longv;
typedef int intv;
#define VLOAD(o, p) ((p)[o])
#define VSTORE(x, o, p) ((p)[o] = (x))
#define CONVERT_INTV convert_int
#elif VW == 2 || VW == 4 || VW == 8 || VW == 16
typedef CAT(REAL_NAME, VW) realv;
typedef CAT(LONG_NAME, VW) longv;
typedef CAT(int, VW) intv;
#define VLOAD(o, p) CAT(vload, VW)((o), (p))
#define VSTORE(x, o, p) CAT(vstore, VW)((x), (o), (p))
#define CONVERT_INTV CAT(convert_int, VW)
#else
#error "VW must be 1, 2, 4, 8 or 16"
#endif

typedef longv maskv;

#if VW == 1
#define AS_LONGV CAT(as_, LONG_NAME)
#define ANY(c) (c)
#define SELECT(a, b, m) ((m) ? (b) : (a))
#define GREATER(a, b) ((LONG_NAME)((a) > (b)))
#define CONVERT_REALV(x) ((real)(x))
#define CONVERT_V(type, x) ((type)(x))
#else
#define AS_LONGV CAT(as_, CAT(LONG_NAME, VW))
#define ANY(c) any(c)
#define SELECT(a, b, m) select((a), (b), (m))
#define GREATER(a, b) isgreater((a), (b))
#define CONVERT_REALV(x) CAT(convert_, CAT(REAL_NAME, VW))(x)
#define CONVERT_V(type, x) CAT(convert_, CAT(type, VW))(x)
#endif

#endif
