/* A tight single-threaded C reference of cloth_warp's semi-implicit substep, for benchmark ratios.

   Same work as the Warp kernels without strain limiting: linear springs with damping along the spring,
   Choi-Ko bend triples (the arc-relative energy of kernels/forces.py, in its algebra: straight triples
   skipped, four divisions, three forces), per-triangle linear drag with corner weights, gravity, pins,
   symplectic Euler. Forces are scattered straight into one array, as the Warp kernels do.
   Built at benchmark time with the system compiler (-O3 -march=native) and called through ctypes. */
#include <math.h>
#include <string.h>

typedef struct { float x, y, z; } v3;
static inline v3 add(v3 a, v3 b) { v3 r = {a.x + b.x, a.y + b.y, a.z + b.z}; return r; }
static inline v3 sub(v3 a, v3 b) { v3 r = {a.x - b.x, a.y - b.y, a.z - b.z}; return r; }
static inline v3 mul(v3 a, float s) { v3 r = {a.x * s, a.y * s, a.z * s}; return r; }
static inline float dot(v3 a, v3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static inline float len(v3 a) { return sqrtf(dot(a, a)); }
static inline v3 cross(v3 a, v3 b) { v3 r = {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; return r; }
static inline void acc(v3 *f, int i, v3 d) { f[i].x += d.x; f[i].y += d.y; f[i].z += d.z; }

static const float P4 = -11.541f, P3 = 34.193f, P2 = -39.083f, P1 = 23.116f, P0 = -9.713f;

void substeps(int steps, int n, int s_count, int t_count, const int *springs, const int *middle, const float *rest,
              const float *k, const float *c, const int *law, const int *tris, const float *drag, const float *weights,
              const float *mass, const int *pinned, const float *target, float gx, float gy, float gz, float wx,
              float wy, float wz, float dt, float *xs, float *vs, float *fs) {
    v3 *x = (v3 *)xs, *v = (v3 *)vs, *f = (v3 *)fs;
    const v3 *tg = (const v3 *)target;
    const v3 g = {gx, gy, gz}, wind = {wx, wy, wz};
    const float R0 = P4 + P3 + P2 + P1 + P0, R1 = -(4 * P4 + 3 * P3 + 2 * P2 + P1), R2 = 6 * P4 + 3 * P3 + P2,
                R3 = -(4 * P4 + P3), R4 = P4;
    for (int step = 0; step < steps; ++step) {
        for (int i = 0; i < n; ++i) f[i] = mul(g, mass[i]);
        for (int s = 0; s < s_count; ++s) {
            int a = springs[2 * s], b = springs[2 * s + 1];
            if (law[s] == 0) {
                v3 d = sub(x[a], x[b]);
                float l = len(d);
                if (l < 1e-9f) continue;
                v3 nrm = mul(d, 1.0f / l);
                float mag = -(k[s] * (l - rest[s]) + c[s] * dot(sub(v[a], v[b]), nrm));
                acc(f, a, mul(nrm, mag));
                acc(f, b, mul(nrm, -mag));
            } else {
                int m = middle[s];
                v3 e1 = sub(x[m], x[a]), e2 = sub(x[b], x[m]), ch = sub(x[b], x[a]);
                float l1 = len(e1), l2 = len(e2), lc = len(ch), arc = l1 + l2;
                if (l1 < 1e-9f || l2 < 1e-9f || lc < 1e-9f || lc >= arc) continue;
                float inv_arc = 1.0f / arc, sr = lc * inv_arc, t = 1.0f - sr;
                float p = (((P4 * sr + P3) * sr + P2) * sr + P1) * sr + P0;
                float integral = t * (R0 + t * (R1 / 2 + t * (R2 / 3 + t * (R3 / 4 + t * R4 / 5))));
                float scale = -4.0f * k[s] * inv_arc * inv_arc;
                float fb = scale * p, gg = scale * (p * sr - integral);
                v3 fc = mul(ch, fb / lc);
                v3 fa = sub(mul(e1, gg / l1), fc), fe = sub(fc, mul(e2, gg / l2));
                acc(f, a, fa);
                acc(f, b, fe);
                acc(f, m, mul(add(fa, fe), -1.0f));
            }
        }
        for (int t = 0; t < t_count; ++t) {
            int a = tris[3 * t], b = tris[3 * t + 1], cc = tris[3 * t + 2];
            v3 cr = cross(sub(x[b], x[a]), sub(x[cc], x[a]));
            float tw = len(cr);
            if (tw < 1e-9f) continue;
            const float *w = weights + 3 * t;
            v3 vr = sub(add(add(mul(v[a], w[0]), mul(v[b], w[1])), mul(v[cc], w[2])), wind);
            v3 ft = mul(cr, -drag[t] * dot(cr, vr) / (2.0f * tw));
            acc(f, a, mul(ft, w[0]));
            acc(f, b, mul(ft, w[1]));
            acc(f, cc, mul(ft, w[2]));
        }
        for (int i = 0; i < n; ++i) {
            if (pinned[i]) {
                v[i] = mul(sub(tg[i], x[i]), 1.0f / dt);
                x[i] = tg[i];
            } else {
                v[i] = add(v[i], mul(f[i], dt / mass[i]));
                x[i] = add(x[i], mul(v[i], dt));
            }
        }
    }
}
