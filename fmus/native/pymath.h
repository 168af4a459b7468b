/*
 * pymath.h - the few Python float operations whose C spelling gives other bits.
 *
 * The native models must agree with fmus/model bit for bit where they can. Python's float
 * arithmetic is IEEE 754 double arithmetic evaluated left to right, and math.sin, cos, atan2,
 * fmod, ceil call the C library's functions directly: written in the same order (and compiled
 * with -ffp-contract=off, no -ffast-math, so no fused multiply-add changes a rounding), C gets
 * the same bits from the same libm. Three operations differ:
 *
 * - math.hypot is not libm's hypot. CPython (3.8+) computes it with its own vector_norm: a
 *   lossless scaling by a power of two, exact squares, compensated summation and one
 *   differential correction of the square root, correctly rounded in nearly every case. glibc's
 *   hypot is accurate to within an ulp but not the same function: on 2 million random pairs of
 *   this project's magnitudes the two differed in the last bit for 3790 pairs (0.19 %, measured
 *   with glibc 2.36 and CPython 3.11.7). py_hypot below is the same algorithm (Ogita, Rump and
 *   Oishi's error-free transformations; the exact square by Dekker's split, as CPython 3.11's
 *   dl_mul computes it: its math module calls no fma), so the distances agree to the last bit too.
 * - min() and max() of Python return their first argument unless the second compares
 *   smaller/greater, so a NaN in the first place stays; C's fmin/fmax drop NaNs.
 * - Python raises ZeroDivisionError on x / 0.0 and ValueError on math.sin(inf); C carries on
 *   with inf or NaN. Those cases end in a refusal either way (the pythonfmu FMU refuses the
 *   exception, the native one the non-finite state or outputs it leads to), with other words.
 */
#ifndef PLATOON_PYMATH_H
#define PLATOON_PYMATH_H

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* Python's min(a, b) and max(a, b) for floats. */
static inline double py_min(double a, double b) { return b < a ? b : a; }
static inline double py_max(double a, double b) { return b > a ? b : a; }

/* x as an exact sum hi + lo of two halves of 26 bits (Dekker's split, Veltkamp's constant). */
static inline void py_split(double x, double *hi, double *lo)
{
    double t = x * 134217729.0; /* 2^27 + 1 */
    *hi = t - (t - x);
    *lo = x - *hi;
}

/* x * y exactly, as hi + lo (Dekker's product). */
static inline void py_exact_product(double x, double y, double *hi, double *lo)
{
    double xh, xl, yh, yl;
    py_split(x, &xh, &xl);
    py_split(y, &yh, &yl);
    double p = xh * yh;
    double q = xh * yl + xl * yh;
    *hi = p + q;
    *lo = p - *hi + q + xl * yl;
}

/* CPython's vector_norm for two nonnegative finite numbers, max their maximum > 0. */
static double py_norm2(double a, double b, double max)
{
    /* frexp(max, &max_e) and scale = ldexp(1.0, -max_e), read and written as IEEE bits (exact
     * either way; the library calls were a tenth of a Vehicle step) */
    uint64_t bits;
    memcpy(&bits, &max, sizeof bits);
    int biased = (int)(bits >> 52 & 0x7ff);
    if (biased == 0) { /* subnormal: 2^-max_e would overflow; scale up first */
        return DBL_MIN * py_norm2(a / DBL_MIN, b / DBL_MIN, max / DBL_MIN);
    }
    int max_e = biased - 1022; /* max = m 2^max_e with 0.5 <= m < 1 */
    double scale, unscale = 0.0;
    if (max_e < 1023) {
        uint64_t scale_bits = (uint64_t)(1023 - max_e) << 52;
        memcpy(&scale, &scale_bits, sizeof scale);
        uint64_t unscale_bits = (uint64_t)(1023 + max_e) << 52; /* 2^max_e, max_e >= -1021 here */
        memcpy(&unscale, &unscale_bits, sizeof unscale);
    } else { /* 2^-1023 or 2^-1024 is subnormal */
        scale = ldexp(1.0, -max_e);
    }
    double csum = 1.0, frac1 = 0.0, frac2 = 0.0;
    double values[2] = {a, b};
    for (int i = 0; i < 2; ++i) {
        double x = values[i] * scale; /* lossless */
        double square, square_low;
        py_exact_product(x, x, &square, &square_low);
        double sum = csum + square; /* fast two-sum: csum >= 1 > square */
        double sum_low = (csum - sum) + square;
        csum = sum;
        frac1 += square_low;
        frac2 += sum_low;
    }
    double h = sqrt(csum - 1.0 + (frac1 + frac2));
    double product, product_low;
    py_exact_product(-h, h, &product, &product_low);
    double sum = csum + product;
    double sum_low = (csum - sum) + product;
    csum = sum;
    frac1 += product_low;
    frac2 += sum_low;
    double x = csum - 1.0 + (frac1 + frac2);
    h += x / (2.0 * h); /* differential correction */
    /* h / scale: dividing by a power of two is exact here (the result, about max, is a normal
     * number), and so is multiplying by its reciprocal 2^max_e, which costs a fifth of a division */
    return unscale != 0.0 ? h * unscale : h / scale;
}

/* math.hypot(x, y) as CPython computes it. */
static inline double py_hypot(double x, double y)
{
    double a = fabs(x), b = fabs(y);
    if (isinf(a) || isinf(b)) return INFINITY;
    if (isnan(a) || isnan(b)) return NAN;
    double max = a > b ? a : b;
    if (max == 0.0) return max;
    return py_norm2(a, b, max);
}

#endif
