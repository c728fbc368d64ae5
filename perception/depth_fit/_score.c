/* The depth fit's score of each fit (R, t) of an object against the frame, one row at a time: called through ctypes
   by ``perception.depth_fit.score``, whose module doc defines it. Camera-frame metres, row-major float32. */

#include <math.h>
#include <stdlib.h>

#include "_kernels.h"
#include "_parallel.h"

/* torch.lerp's a + w (b - a), from the nearer end. */
static inline float lerp(float a, float b, float w) { return w < 0.5f ? a + w * (b - a) : b - (b - a) * (1.0f - w); }

/* The distance of the object-frame point x (3) to object o's surface: the trilinear interpolation of its field's
   cell, made unsigned; the field's margin beyond it. */
static inline float field_distance(const struct fields *f, int64_t o, const float x[3]) {
    const float *lo = f->lo + 3 * o, *top = f->top + 3 * o;
    const int32_t *st = f->strides + 3 * o;
    float c = f->cell[o], u[3], w[3];
    int32_t base = f->start[o];
    for (int a = 0; a < 3; a++) {
        u[a] = (x[a] - lo[a]) / c;
        if (u[a] < 0 || u[a] > top[a]) return f->margin[o];
        float i = floorf(u[a]);
        i = i > top[a] - 1 ? top[a] - 1 : i;
        i = i < 0 ? 0 : i;
        w[a] = u[a] - i;
        w[a] = w[a] < 0 ? 0 : (w[a] > 1 ? 1 : w[a]);
        base += (int32_t)i * st[a];
    }
    const float *v = f->values + base;
    int32_t sx = st[0], sy = st[1], sz = st[2];
    float v00 = lerp(v[0], v[sz], w[2]), v01 = lerp(v[sy], v[sy + sz], w[2]);
    float v10 = lerp(v[sx], v[sx + sz], w[2]), v11 = lerp(v[sx + sy], v[sx + sy + sz], w[2]);
    return fabsf(lerp(lerp(v00, v01, w[1]), lerp(v10, v11, w[1]), w[0]));
}

/* The distance of the object-frame point x (3) to the model point object o's grid stores for its cell. */
static inline float grid_distance(const struct grids *g, const float *table, int64_t o, const float x[3]) {
    const float *lo = g->lo + 3 * o, *last = g->last + 3 * o, *st = g->strides + 3 * o;
    float c = g->cell[o], flat = 0;
    for (int a = 0; a < 3; a++) {
        float u = (x[a] - lo[a]) / c;
        u = u < 0 ? 0 : (u > last[a] ? last[a] : u);
        flat += st[a] * posegrasp_round(u);
    }
    const float *q = table + 3 * (int64_t)g->index[(int32_t)flat + g->start[o]];
    float d0 = x[0] - q[0], d1 = x[1] - q[1], d2 = x[2] - q[2];
    return sqrtf(d0 * d0 + d1 * d1 + d2 * d2);
}

/* The fit term of row (R, t) of object o: the weighted mean truncated distance of its observed points. */
static double fit_term(const struct observed *obs, const struct grids *g, const struct fields *f, int64_t o,
                       const float *R, const float *t, float truncation) {
    const float *p = obs->points + o * obs->n * 3, *w = obs->weights + o * obs->n;
    double sum = 0, total = 0;
    for (int64_t i = 0; i < obs->n; i++) {
        if (w[i] == 0) continue;
        float d[3] = {p[3 * i] - t[0], p[3 * i + 1] - t[1], p[3 * i + 2] - t[2]}, x[3];
        for (int a = 0; a < 3; a++) x[a] = R[a] * d[0] + R[3 + a] * d[1] + R[6 + a] * d[2];  /* R^T (p - t) */
        float dist = f != NULL ? field_distance(f, o, x) : grid_distance(g, obs->table, o, x);
        sum += (double)w[i] * (dist < truncation ? dist : truncation);
        total += w[i];
    }
    return total > 0 ? sum / total : 0;
}

/* The counts of the k model points m (k, 3) at (R, t) that are valid (``ok``), seen (projected into the image),
   seen in front of the seen surface and (given the plane) beneath it, and the lowest one's height above the plane;
   ``pix``, ``z`` and ``height`` (k) are scratch. */
struct model_terms {
    int64_t valid, seen, in_front, beneath;
    float lowest;
};

static struct model_terms POSEGRASP_CLONES model_terms(const struct scene *sc, float margin, const float *m,
                                                       const uint8_t *ok, int64_t k, const float *R, const float *t,
                                                       int32_t *restrict pix, float *restrict z,
                                                       float *restrict height) {
    static const float level[4] = {0, 0, 0, 0};
    struct model_terms out = {0, 0, 0, 0, INFINITY};
    const float *pl = sc->plane != NULL ? sc->plane : level;
    const float w = (float)sc->width, h = (float)sc->height;
    int64_t valid = 0, beneath = 0;
    for (int64_t j = 0; j < k; j++) {  /* this loop vectorises: no branch, no gather */
        float c0 = R[0] * m[3 * j] + R[1] * m[3 * j + 1] + R[2] * m[3 * j + 2] + t[0];
        float c1 = R[3] * m[3 * j] + R[4] * m[3 * j + 1] + R[5] * m[3 * j + 2] + t[1];
        float c2 = R[6] * m[3 * j] + R[7] * m[3 * j + 1] + R[8] * m[3 * j + 2] + t[2];
        float zj = c2 > 1e-6f ? c2 : 1e-6f;
        float u = c0 * sc->fx / zj + sc->cx, v = c1 * sc->fy / zj + sc->cy;
        u = posegrasp_round(u < -2 ? -2 : (u > w + 1 ? w + 1 : u));  /* clamped beyond the image, then rounded */
        v = posegrasp_round(v < -2 ? -2 : (v > h + 1 ? h + 1 : v));
        int valid_j = ok[j] != 0, inside = valid_j & (u >= 0) & (u < w) & (v >= 0) & (v < h);
        pix[j] = inside ? (int32_t)v * (int32_t)sc->width + (int32_t)u : -1;
        z[j] = zj;
        float above = c0 * pl[0] + c1 * pl[1] + c2 * pl[2] + pl[3];
        height[j] = valid_j ? above : INFINITY;
        valid += valid_j;
        beneath += valid_j & (above < -margin);
    }
    out.valid = valid, out.beneath = sc->plane != NULL ? beneath : 0;
    for (int64_t j = 0; j < k; j++) {
        out.lowest = height[j] < out.lowest ? height[j] : out.lowest;
        if (pix[j] < 0) continue;
        float dz = sc->depth[pix[j]];
        out.seen++;
        out.in_front += dz > 0 && z[j] < dz - margin;
    }
    return out;
}

/* A batch of scores (``posegrasp_scores``' arguments). */
struct score_work {
    const struct observed *obs;
    const struct grids *g;
    const struct fields *f;
    const struct scene *sc;
    const struct score_config *cfg;
    int64_t k;
    const float *R, *t;
    float *out;
};

/* The scores of rows [begin, end) of a batch: 0, or -1 out of memory. */
static int score_rows(void *arg, int64_t begin, int64_t end) {
    const struct score_work *wk = arg;
    const struct score_config *cfg = wk->cfg;
    const struct scene *sc = wk->sc;
    const float *pl = sc->plane;
    int64_t k = wk->k;
    int32_t *pix = malloc(k * sizeof(int32_t));
    float *z = malloc(2 * k * sizeof(float));
    if (pix == NULL || z == NULL) {
        free(pix), free(z);
        return -1;
    }
    for (int64_t h = begin; h < end; h++) {
        int64_t o = wk->obs->obj[h];
        const float *Rh = wk->R + 9 * h, *th = wk->t + 3 * h;
        double score = fit_term(wk->obs, wk->g, wk->f, o, Rh, th, cfg->truncation);
        struct model_terms mt = model_terms(sc, cfg->violation_margin, sc->models + o * sc->m * 3, sc->ok + o * sc->m,
                                            k, Rh, th, pix, z, z + k);
        double violation = (double)mt.in_front / (mt.seen > 1 ? mt.seen : 1);
        if (pl != NULL) {
            float lowest = mt.lowest;
            violation += (double)mt.beneath / (mt.valid > 1 ? mt.valid : 1);
            if (sc->supports != NULL) {  /* the highest support not above the lowest point (the plane, 0, at least) */
                const float *sup = sc->supports + o * sc->s;
                float best = 0;
                for (int64_t i = 0; i < sc->s; i++)
                    if (sup[i] <= lowest + cfg->float_margin && sup[i] > best) best = sup[i];
                lowest -= best;
            }
            float floating = (lowest - cfg->float_margin) / 0.01f;
            score += cfg->float_weight * (floating < 0 ? 0 : (floating > 1 ? 1 : floating));
        }
        wk->out[h] = (float)(score + cfg->violation_weight * violation);
    }
    free(pix), free(z);
    return 0;
}

/* The scores (H,) (m) of the fits R (H, 3, 3), t (H, 3) of objects obs->obj, on the first k model points; with
   ``f`` (the fine scores) the distances from the fields, else to the grids' model points. The rows run on up to
   ``threads`` threads (``posegrasp_parallel``). Returns 0, or -1 out of memory. */
int posegrasp_scores(const struct observed *obs, const struct grids *g, const struct fields *f,
                     const struct scene *sc, const struct score_config *cfg, int64_t k, const float *R,
                     const float *t, float *out, int64_t threads) {
    struct score_work work = {obs, g, f, sc, cfg, k, R, t, out};
    return posegrasp_parallel(score_rows, &work, obs->rows, threads);
}
