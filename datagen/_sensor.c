/* The depth camera model's per-pixel steps (``datagen.noise``, whose docstrings define them) and the renderer's depth
   conversion (``datagen.render``), called through ctypes. Each computes the same float32 (or float64) operations, in
   the same order, as numpy's whole-image formulas it replaces, so the images are the same bit for bit; row-major
   (H, W) images. Built without FMA contraction: a fused multiply-add would round once where numpy rounds twice. */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* The least and greatest of each pixel's row neighbours (c - 1, c, c + 1 within the row) of row x (W), invalid depth
   (<= 0) counted as 1000 m; v (W + 2): scratch, the row between copies of its end pixels. */
static void row_extremes(const float *x, int64_t W, float *v, float *lo, float *hi) {
    for (int64_t c = 0; c < W; c++) v[c + 1] = x[c] > 0 ? x[c] : 1e3f;
    v[0] = v[1];
    v[W + 1] = v[W];
    for (int64_t c = 0; c < W; c++) {
        float a = v[c] < v[c + 2] ? v[c] : v[c + 2], b = v[c] > v[c + 2] ? v[c] : v[c + 2];
        lo[c] = v[c + 1] < a ? v[c + 1] : a;
        hi[c] = v[c + 1] > b ? v[c + 1] : b;
    }
}

/* drop[i] = 1 where pixel i lies in the projector's shadow (its column u - fb / z left of the least such column of a
   pixel right of it, by more than tol) or on a depth edge (its 3 x 3 neighbourhood, invalid depth counted as 1000 m,
   spans more than threshold); else 0. Returns -1 when out of memory. */
int posegrasp_depth_drop(const float *depth, int64_t H, int64_t W, float fb, float tol, float threshold,
                         uint8_t *drop) {
    float *up = malloc(sizeof(float) * (size_t)(7 * W + 2));  /* up (or scratch); each row's least, greatest: 3 rows */
    if (up == NULL) return -1;
    float *lo = up + W + 2, *hi = lo + 3 * W;
    for (int64_t r = 0; r < H; r++) {
        const float *d = depth + r * W;
        uint8_t *out = drop + r * W;
        for (int32_t c = 0; c < (int32_t)W; c++) up[c] = (float)c - (d[c] > 0 ? fb / d[c] : 0.0f);
        float least = up[W - 1];  /* the least column of the pixels right of c */
        out[W - 1] = 0;
        for (int64_t c = W - 2; c >= 0; c--) {
            out[c] = up[c] > least + tol && d[c] > 0;
            least = up[c] < least ? up[c] : least;
        }
    }
    for (int64_t r = 0; r < H; r++) {  /* row k's extremes in slot k % 3, made once each */
        int64_t r0 = r > 0 ? r - 1 : r, r1 = r < H - 1 ? r + 1 : r;
        for (int64_t k = r == 0 ? r0 : r1; k <= r1; k++)
            row_extremes(depth + k * W, W, up, lo + k % 3 * W, hi + k % 3 * W);
        const float *l0 = lo + r0 % 3 * W, *l1 = lo + r % 3 * W, *l2 = lo + r1 % 3 * W;
        const float *h0 = hi + r0 % 3 * W, *h1 = hi + r % 3 * W, *h2 = hi + r1 % 3 * W;
        uint8_t *out = drop + r * W;
        for (int64_t c = 0; c < W; c++) {
            float l = l0[c] < l1[c] ? l0[c] : l1[c], h = h0[c] > h1[c] ? h0[c] : h1[c];
            l = l < l2[c] ? l : l2[c];
            h = h > h2[c] ? h : h2[c];
            out[c] |= h - l > threshold;
        }
    }
    free(up);
    return 0;
}

/* The pixel offset of a 16-bit uniform u: +1 from t2, +2 from t3, -1 below t1, -2 below t0. */
static inline int8_t offset(uint16_t u, const int32_t t[4]) {
    return (int8_t)((u >= t[2]) + (u >= t[3]) - (u < t[1]) - (u < t[0]));
}

/* z (H, W): each pixel the depth of the pixel shifted by the offsets of the uniforms u (2, H, W) (x then y), clamped
   to the image (OpenCV's nearest remap, replicated border). Returns -1 when out of memory. */
int posegrasp_shifted(const float *depth, int64_t H, int64_t W, const uint16_t *u, const int32_t t[4], float *z) {
    int8_t *kx = malloc(2 * (size_t)W), *ky = kx + W;
    if (kx == NULL) return -1;
    const int32_t s[4] = {t[0], t[1], t[2], t[3]};
    for (int64_t r = 0; r < H; r++) {
        const uint16_t *ux = u + r * W, *uy = u + H * W + r * W;
        for (int64_t c = 0; c < W; c++) {  /* (the offsets first: a loop of them vectorises) */
            kx[c] = offset(ux[c], s);
            ky[c] = offset(uy[c], s);
        }
        for (int64_t c = 0; c < W; c++) {
            int64_t x = c + kx[c], y = r + ky[c];
            x = x < 0 ? 0 : (x >= W ? W - 1 : x);
            y = y < 0 ? 0 : (y >= H ? H - 1 : y);
            z[r * W + c] = depth[y * W + x];
        }
    }
    free(kx);
    return 0;
}

/* The phase's arguments: x = z where valid (> 0), else 1; y = grad * k. */
void posegrasp_phase_args(const float *z, const float *grad, int64_t n, float k, float *x, float *y) {
    for (int64_t i = 0; i < n; i++) {
        x[i] = z[i] > 0 ? z[i] : 1.0f;
        y[i] = grad[i] * k;
    }
}

/* The noise model's constants, float32 as numpy rounds them. */
struct depth_noise {
    float theta_max, z_ref, sigma_quad, sigma_base, half_pi, sigma_angle, fb, step, edge_dropout, keep_below, near,
        far;
};

/* numpy's minimum and maximum of x and a number c: NaN where x is NaN. */
static inline float least(float x, float c) { return x > c ? c : x; }
static inline float greatest(float x, float c) { return x < c ? c : x; }

/* x rounded to the nearest integer, ties to even (rintf, without a library call: a loop of it vectorises). */
static inline float round_even(float x) {
    float a = fabsf(x), r = a < 8388608.0f ? (a + 8388608.0f) - 8388608.0f : a;  /* 2^23: the first float step of 1 */
    return copysignf(r, x);
}

/* The measured depth of each pixel from its shifted depth z, incidence angle theta, standard normal draw and uniform
   draw u, and drop (shadow or edge): axial noise, disparity quantisation, dropout; 0 where lost or out of range. */
void posegrasp_depth_noise(const float *z, const float *theta, const float *normal, const float *u,
                           const uint8_t *drop, int64_t n, const struct depth_noise *p, float *out) {
    const struct depth_noise q = *p;
    for (int64_t i = 0; i < n; i++) {
        float zi = z[i], th = least(theta[i], q.theta_max);
        float sigma = zi - q.z_ref;
        sigma *= sigma;
        sigma *= q.sigma_quad;
        sigma += q.sigma_base;
        float grazing = q.half_pi - th;
        grazing *= grazing;
        grazing *= sqrtf(greatest(zi, 1e-3f));
        th *= th;
        th *= q.sigma_angle;
        sigma += th / grazing;
        float noisy = zi + sigma * normal[i];
        float disp = round_even(q.fb / greatest(noisy, 1e-3f) / q.step) * q.step;
        float m = q.fb / greatest(disp, 1e-6f);
        m *= (float)(disp > 0);
        int lost = ((drop[i] != 0) & (u[i] < q.edge_dropout)) | (u[i] >= q.keep_below) | !(zi > 0);
        lost |= (m < q.near) | (m > q.far);
        out[i] = m * (float)!lost;
    }
}

/* Metres along the optical axis from MuJoCo's reversed-Z depth buffer raw (H, W, bottom row first), d / (raw + c) in
   float64 rounded to float32, 0 outside [near, far]; rows flipped to top first. */
void posegrasp_metric_depth(const float *raw, int64_t H, int64_t W, float c, float d, float near, float far,
                            float *out) {
    for (int64_t r = 0; r < H; r++)
        for (int64_t k = 0; k < W; k++) {
            float z = (float)((double)d / ((double)raw[r * W + k] + (double)c));
            out[(H - 1 - r) * W + k] = z < near || z > far ? 0.0f : z;
        }
}
