/* The depth fit's ICP steps, one row (a fit of one object) at a time: called through ctypes by
   ``perception.depth_fit.icp``. Each step matches each observed point p_i (weight
   w_i, normalised to sum to 1) to a model point m_i, the model point stored for the voxel-grid cell of
   R^T (p_i - t) (``perception.depth_fit.grids``) or the nearest one, and refits (R, t):

   free rows: R = argmax tr(R C), C = sum_i m_i (w_i (p_i - c_p))^T, by Horn's unit quaternion, the eigenvector of
   the largest eigenvalue of the symmetric 4x4 matrix of C (Jacobi rotations, double precision), or R unchanged where
   every point is matched to one model point (C = 0: no rotation is pinned); t = c_p - R c_m;
   held rows (resting on the plane n . x + d = 0): R = G(a) R0, a = atan2(B, A), A = tr C' - n^T C' n,
   B = n . (C'_yz - C'_zy, C'_zx - C'_xz, C'_xy - C'_yx), C' = R0 C; then t moved along n to set the row back resting
   on the plane: its lowest model point's height, ``low`` + n . t + d, made 0. Camera-frame metres, row-major float32
   matrices. */

#include <math.h>
#include <stdlib.h>

#include "_kernels.h"
#include "_parallel.h"

/* The rotation R (3x3) maximising tr(R C) for C[a][b] = sum_i s_a d_b (Horn 1987). */
static void horn_rotation(const double C[9], double R[9]) {
    double xx = C[0], xy = C[1], xz = C[2], yx = C[3], yy = C[4], yz = C[5], zx = C[6], zy = C[7], zz = C[8];
    double A[4][4] = {{xx + yy + zz, yz - zy, zx - xz, xy - yx},
                      {yz - zy, xx - yy - zz, xy + yx, zx + xz},
                      {zx - xz, xy + yx, -xx + yy - zz, yz + zy},
                      {xy - yx, zx + xz, yz + zy, -xx - yy + zz}};
    double V[4][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}};
    for (int sweep = 0; sweep < 32; sweep++) {
        double off = 0, diag = 0;
        for (int i = 0; i < 4; i++) {
            diag += A[i][i] * A[i][i];
            for (int j = i + 1; j < 4; j++) off += A[i][j] * A[i][j];
        }
        if (off <= 1e-30 * diag || off == 0) break;
        for (int p = 0; p < 3; p++)
            for (int q = p + 1; q < 4; q++) {
                if (A[p][q] == 0) continue;
                double theta = (A[q][q] - A[p][p]) / (2 * A[p][q]);
                double tn = (theta >= 0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1));
                double c = 1 / sqrt(tn * tn + 1), s = tn * c;
                for (int k = 0; k < 4; k++) {
                    double kp = A[k][p], kq = A[k][q];
                    A[k][p] = c * kp - s * kq;
                    A[k][q] = s * kp + c * kq;
                }
                for (int k = 0; k < 4; k++) {
                    double pk = A[p][k], qk = A[q][k];
                    A[p][k] = c * pk - s * qk;
                    A[q][k] = s * pk + c * qk;
                    double vp = V[k][p], vq = V[k][q];
                    V[k][p] = c * vp - s * vq;
                    V[k][q] = s * vp + c * vq;
                }
            }
    }
    int b = 0;
    for (int i = 1; i < 4; i++)
        if (A[i][i] > A[b][b]) b = i;
    double w = V[0][b], x = V[1][b], y = V[2][b], z = V[3][b];
    double norm = sqrt(w * w + x * x + y * y + z * z);
    w /= norm, x /= norm, y /= norm, z /= norm;
    R[0] = w * w + x * x - y * y - z * z, R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z), R[4] = w * w - x * x + y * y - z * z, R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = w * w - x * x - y * y + z * z;
}

/* R0 (3x3) turned about the unit normal n by the turn that best fits C (module comment): G(a) R0. */
static void held_rotation(const double C[9], const float R0[9], const float n[3], double R[9]) {
    double Ch[9], G[9], nCn = 0;
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            Ch[3 * a + b] = R0[3 * a] * C[b] + R0[3 * a + 1] * C[3 + b] + R0[3 * a + 2] * C[6 + b];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) nCn += n[a] * Ch[3 * a + b] * n[b];
    double A = Ch[0] + Ch[4] + Ch[8] - nCn;
    double B = n[0] * (Ch[5] - Ch[7]) + n[1] * (Ch[6] - Ch[2]) + n[2] * (Ch[1] - Ch[3]);
    double angle = atan2(B, A), s = sin(angle), c = 1 - cos(angle);
    double N[9] = {0, -n[2], n[1], n[2], 0, -n[0], -n[1], n[0], 0};  /* N v = n x v */
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) {
            double NN = N[3 * a] * N[b] + N[3 * a + 1] * N[3 + b] + N[3 * a + 2] * N[6 + b];
            G[3 * a + b] = (a == b) + s * N[3 * a + b] + c * NN;  /* Rodrigues */
        }
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            R[3 * a + b] = G[3 * a] * R0[b] + G[3 * a + 1] * R0[3 + b] + G[3 * a + 2] * R0[6 + b];
}

/* Rows of ``table`` matched to the m observed points (x, y, z) in the frame (R, t) of object o. */
static void POSEGRASP_CLONES grid_matches(const struct grids *g, int64_t o, const float *R, const float *t,
                                          const float *restrict x, const float *restrict y, const float *restrict z,
                                          int64_t m, int32_t *restrict out) {
    float s = 1.0f / g->cell[o], A[9], off[3];
    const float *lo = g->lo + 3 * o, *last = g->last + 3 * o, *st = g->strides + 3 * o;
    for (int a = 0; a < 3; a++) {  /* cell coordinates (R^T p - R^T t - lo) / cell */
        for (int b = 0; b < 3; b++) A[3 * a + b] = R[3 * b + a] * s;
        off[a] = (t[0] * R[a] + t[1] * R[3 + a] + t[2] * R[6 + a] + lo[a]) * s;
    }
    const float l0 = last[0], l1 = last[1], l2 = last[2], s0 = st[0], s1 = st[1], s2 = st[2];
    const int32_t first = g->start[o];
    for (int64_t i = 0; i < m; i++) {  /* the flat cells (this loop vectorises), then their rows */
        float c0 = A[0] * x[i] + A[1] * y[i] + A[2] * z[i] - off[0];
        float c1 = A[3] * x[i] + A[4] * y[i] + A[5] * z[i] - off[1];
        float c2 = A[6] * x[i] + A[7] * y[i] + A[8] * z[i] - off[2];
        c0 = c0 < 0 ? 0 : (c0 > l0 ? l0 : c0);
        c1 = c1 < 0 ? 0 : (c1 > l1 ? l1 : c1);
        c2 = c2 < 0 ? 0 : (c2 > l2 ? l2 : c2);
        out[i] = (int32_t)(s0 * posegrasp_round(c0) + s1 * posegrasp_round(c1) + s2 * posegrasp_round(c2)) + first;
    }
    for (int64_t i = 0; i < m; i++) out[i] = g->index[out[i]];
}

/* The table row of the model point of object o nearest the object-frame point x (3), searched in the buckets the
   cube x +- r meets, r the distance of x to the model point ``row`` (ties: the lower row). */
static int32_t nearest(const struct buckets *b, const float *table, int64_t o, const float x[3], int32_t row) {
    const float *q = table + 3 * (int64_t)row, *lo = b->lo + 3 * o;
    float best = (x[0] - q[0]) * (x[0] - q[0]) + (x[1] - q[1]) * (x[1] - q[1]) + (x[2] - q[2]) * (x[2] - q[2]);
    float r = sqrtf(best), size = b->size[o];
    const int32_t *shape = b->shape + 3 * o, *first = b->first + b->start[o];
    int32_t from[3], to[3];
    for (int a = 0; a < 3; a++) {  /* the cubes the box meets, clamped to the grid (which holds every point) */
        float u0 = floorf((x[a] - r - lo[a]) / size), u1 = floorf((x[a] + r - lo[a]) / size);
        from[a] = u0 < 0 ? 0 : (u0 > shape[a] - 1 ? shape[a] - 1 : (int32_t)u0);
        to[a] = u1 < 0 ? 0 : (u1 > shape[a] - 1 ? shape[a] - 1 : (int32_t)u1);
    }
    for (int32_t i = from[0]; i <= to[0]; i++)
        for (int32_t j = from[1]; j <= to[1]; j++) {
            int32_t k0 = (i * shape[1] + j) * shape[2];
            for (int32_t e = first[k0 + from[2]]; e < first[k0 + to[2] + 1]; e++) {
                int32_t s = b->rows[e];
                const float *p = table + 3 * (int64_t)s;
                float d = (x[0] - p[0]) * (x[0] - p[0]) + (x[1] - p[1]) * (x[1] - p[1]) + (x[2] - p[2]) * (x[2] - p[2]);
                if (d < best || (d == best && s < row)) best = d, row = s;
            }
        }
    return row;
}

/* C (3x3) and the weighted mean c_m (3) of the model points table[rows] against the weighted, centred observed
   points d (m, 4: w_i (p_i - c_p), w_i). */
static void POSEGRASP_CLONES covariance(const float *table, const int32_t *rows, const float (*d)[4], int64_t m,
                                        double C[9], double cm[3]) {
    float c0 = 0, c1 = 0, c2 = 0, c3 = 0, c4 = 0, c5 = 0, c6 = 0, c7 = 0, c8 = 0, m0 = 0, m1 = 0, m2 = 0;
    for (int64_t i = 0; i < m; i++) {
        const float *q = table + 3 * (int64_t)rows[i], *e = d[i];
        c0 += q[0] * e[0], c1 += q[0] * e[1], c2 += q[0] * e[2];
        c3 += q[1] * e[0], c4 += q[1] * e[1], c5 += q[1] * e[2];
        c6 += q[2] * e[0], c7 += q[2] * e[1], c8 += q[2] * e[2];
        m0 += q[0] * e[3], m1 += q[1] * e[3], m2 += q[2] * e[3];
    }
    C[0] = c0, C[1] = c1, C[2] = c2, C[3] = c3, C[4] = c4, C[5] = c5, C[6] = c6, C[7] = c7, C[8] = c8;
    cm[0] = m0, cm[1] = m1, cm[2] = m2;
}

/* A batch of ICP steps (``posegrasp_icp_steps``' arguments). */
struct icp_work {
    const struct observed *obs;
    const struct grids *g;
    const struct buckets *b;
    int exact;
    int64_t steps;
    float *R, *t;
    const uint8_t *held;
    const float *low, *plane;
};

/* The steps of rows [begin, end) of a batch: 0, -1 where a row's object has no weight, -2 out of memory. */
static int icp_rows(void *arg, int64_t begin, int64_t end) {
    const struct icp_work *wk = arg;
    const struct observed *obs = wk->obs;
    const float *plane = wk->plane;
    int64_t N = obs->n;
    int status = 0;
    float *x = malloc(N * 3 * sizeof(float)), (*d)[4] = malloc(N * sizeof(*d));
    int32_t *rows = malloc(N * sizeof(int32_t));
    if (!x || !d || !rows) status = -2;
    float *y = x + N, *z = x + 2 * N;
    for (int64_t h = begin; h < end && status == 0; h++) {
        int64_t o = obs->obj[h], m = 0;
        const float *p = obs->points + o * N * 3, *w = obs->weights + o * N;
        double total = 0, cp[3] = {0, 0, 0};
        for (int64_t i = 0; i < N; i++) {
            total += w[i];
            for (int a = 0; a < 3; a++) cp[a] += (double)w[i] * p[3 * i + a];
        }
        if (!(total > 0)) {
            status = -1;
            break;
        }
        for (int64_t i = 0; i < N; i++) {
            if (w[i] == 0) continue;
            double wi = w[i] / total;
            x[m] = p[3 * i], y[m] = p[3 * i + 1], z[m] = p[3 * i + 2];
            for (int a = 0; a < 3; a++) d[m][a] = (float)(wi * (p[3 * i + a] - cp[a] / total));
            d[m++][3] = (float)wi;
        }
        float *Rh = wk->R + 9 * h, *th = wk->t + 3 * h;
        for (int64_t step = 0; step < wk->steps; step++) {
            grid_matches(wk->g, o, Rh, th, x, y, z, m, rows);
            for (int64_t i = 0; i < m && wk->exact; i++) {
                float d[3] = {x[i] - th[0], y[i] - th[1], z[i] - th[2]}, local[3];  /* R^T (p - t) */
                for (int a = 0; a < 3; a++) local[a] = Rh[a] * d[0] + Rh[3 + a] * d[1] + Rh[6 + a] * d[2];
                rows[i] = nearest(wk->b, obs->table, o, local, rows[i]);
            }
            double C[9], cm[3], Rn[9], tn[3];
            covariance(obs->table, rows, (const float (*)[4])d, m, C, cm);
            int one = 1;  /* every point matched to one model point: no rotation is pinned, the row keeps its own */
            for (int64_t i = 1; i < m; i++) one &= rows[i] == rows[0];
            if (wk->held[h]) {
                held_rotation(C, Rh, plane, Rn);
            } else if (!one) {
                horn_rotation(C, Rn);
            } else {
                for (int a = 0; a < 9; a++) Rn[a] = Rh[a];
            }
            for (int a = 0; a < 3; a++)
                tn[a] = cp[a] / total - (Rn[3 * a] * cm[0] + Rn[3 * a + 1] * cm[1] + Rn[3 * a + 2] * cm[2]);
            if (wk->held[h]) {
                double e = wk->low[h] + tn[0] * plane[0] + tn[1] * plane[1] + tn[2] * plane[2] + plane[3];
                for (int a = 0; a < 3; a++) tn[a] -= e * plane[a];
            }
            for (int k = 0; k < 9; k++) Rh[k] = (float)Rn[k];
            for (int a = 0; a < 3; a++) th[a] = (float)tn[a];
        }
    }
    free(x), free(d), free(rows);
    return status;
}

/* ``steps`` ICP steps of every row (R (H, 3, 3), t (H, 3) updated in place), each observed point matched to the
   model point the grids store for its cell, or with ``exact``, to its nearest one (``nearest``). ``held`` (H,),
   ``low`` (H,), ``plane`` (4): the held rows (module comment). The rows run on up to ``threads`` threads
   (``posegrasp_parallel``). Returns 0; -1 where a row's object has no weight, -2 out of memory. */
int posegrasp_icp_steps(const struct observed *obs, const struct grids *g, const struct buckets *b, int exact,
                        int64_t steps, float *R, float *t, const uint8_t *held, const float *low, const float *plane,
                        int64_t threads) {
    struct icp_work work = {obs, g, b, exact, steps, R, t, held, low, plane};
    return posegrasp_parallel(icp_rows, &work, obs->rows, threads);
}
