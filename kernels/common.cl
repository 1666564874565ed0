/* Vector helpers shared by the clsas kernels. VEC (2, 4, 8 or 16) is set with -DVEC=n. */
#ifndef VEC
#define VEC 8
#endif
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define floatV CAT(float, VEC)
#define intV CAT(int, VEC)
#define vloadV CAT(vload, VEC)
#define vstoreV CAT(vstore, VEC)
#define convert_intV CAT(convert_int, VEC)
