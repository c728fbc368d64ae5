/* What the depth fit's compiled kernels (_icp.c, _score.c) read of a frame's ``FitContext``: row-major float32
   arrays, camera-frame metres; the ctypes structures of ``perception.depth_fit.kernels`` mirror these. */

#ifndef POSEGRASP_KERNELS_H
#define POSEGRASP_KERNELS_H

#include <stddef.h>
#include <stdint.h>

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define POSEGRASP_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define POSEGRASP_CLONES
#endif

/* The fits' observed points: points (O, N, 3) and weights (O, N) (0: padding) of each fit's object obj (H,); the
   model points ``table`` (G M, 3) of the distinct grids, which their ``index`` rows name. */
struct observed {
    int64_t rows, n;
    const float *points, *weights;
    const int64_t *obj;
    const float *table;
};

/* The objects' voxel grids (``Grids``): cell corner ``lo`` (O, 3), side ``cell`` (O,), last cell ``last`` (O, 3),
   flat strides (O, 3), each object's first entry ``start`` (O,) in ``index``, the table rows of the cells' nearest
   model points. */
struct grids {
    const float *lo, *cell, *last, *strides;
    const int32_t *start, *index;
};

/* The objects' buckets (``Buckets``) for exact matches: first cube ``lo`` (O, 3), side ``size`` (O,), cubes ``shape``
   (O, 3), each object's first entry ``start`` (O,) in ``first``, where cube k's table rows begin in ``rows`` (and
   cube k + 1's, after them). */
struct buckets {
    const float *lo, *size;
    const int32_t *shape, *start, *first, *rows;
};

/* The objects' signed distance fields (``Fields``): first node ``lo`` (O, 3), side ``cell`` (O,), last node ``top``
   (O, 3), the distance ``margin`` (O,) beyond them, flat strides (O, 3), first entry ``start`` (O,) in ``values``. */
struct fields {
    const float *values, *lo, *cell, *top, *margin;
    const int32_t *strides, *start;
};

/* The objects' model points (O, M, 3), valid where ``ok`` (O, M); the depth image (height, width) (0: none) and the
   pinhole (fx, fy, cx, cy); the plane (4,: n . x + d = 0) or NULL, and the heights (O, S) above it each object may
   rest on (``FitContext.supports``) or NULL. */
struct scene {
    int64_t m, height, width, s;
    const float *models;
    const uint8_t *ok;
    const float *depth;
    float fx, fy, cx, cy;
    const float *plane, *supports;
};

/* ``ScoreConfig``. */
struct score_config {
    float truncation, violation_margin, violation_weight, float_margin, float_weight;
};

/* Rounded half to even, for 0 <= v < 2^22 (the default rounding mode). */
static inline float posegrasp_round(float v) { return (v + 12582912.0f) - 12582912.0f; }

#endif
