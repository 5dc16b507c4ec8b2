/* The hot loops of sdexp's simulator: co-rotated element forces (forces.h; see fem.py and
 * quadratic.py for the math) and whole control steps of substeps (advance). reference.py is the
 * numba twin of both, in the same order and with the same names, and the fallback.
 *
 * Elements are processed in blocks of B: a gather of the edge vectors Ds into
 * structure-of-arrays buffers (scalar; quadratic tets: SIMD gathers from a blocked el), one
 * branch-free loop the compiler turns into SIMD (F = Ds Dm^-1 onwards), a scalar scatter of the
 * forces. This layout is what lets gcc vectorise it; numba's LLVM keeps the same arithmetic
 * scalar. The per-vertex update (kick, drift) is SIMD over vertices too, except with contacts.
 * Threads are OpenMP's: a region costs a microsecond or two, a numba parallel region ten. */
#include <math.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#else
static int omp_get_thread_num(void) { return 0; }
#endif
#define B 32  /* elements per SIMD block */
#define VT 64 /* vertices per tile of the velocity update */
#define POLAR_ITERATIONS 2  /* as reference.POLAR_ITERATIONS */
/* One body and one control step of it; native.Step mirrors this layout. Arrays are C-ordered
 * (rows: vertices or elements), dim = 2 or 3 columns; in 3D el, Bm, vol and q are blocked
 * (forces_impl, p2_forces_blocked). nodes: per element (4 / 3 linear, 10 / 6 quadratic).
 * single: Bm, vol and q are float and the forces are computed in float (sim.precision), else
 * double. mass: the inertial mass (with any added by sim.mass_scaling); gravity_share: physical
 * over inertial mass per vertex (gravity acts on the physical mass), NULL where they are equal. */
typedef struct {
    int64_t dim, nv, ne, nt, n_sub, n_rotors, n_boxes, nodes, single;
    double dt, mu, lam, damping, deform_damping, gravity, ground, friction;
    double *x, *v;
    void *q;
    double *fbuf, *ext, *dirs;
    const double *fext, *minv, *mass;
    const void *Bm, *vol;
    const double *boxes_min, *boxes_max, *weights, *thrust, *gravity_share;
    const int32_t *el;
    const int64_t *face_ptr, *faces, *vert_ptr, *verts;
} Step;

/* The element force kernels, in double (sim.precision = float64) and in float (float32, names
 * ending _f32): one source, forces.h, included once per type. */
#define real double
#define SUFFIX
#define RSQRT sqrt
#define RFABS fabs
#include "forces.h"
#undef real
#undef SUFFIX
#undef RSQRT
#undef RFABS
#define real float
#define SUFFIX _f32
#define RSQRT sqrtf
#define RFABS fabsf
#include "forces.h"
#undef real
#undef SUFFIX
#undef RSQRT
#undef RFABS


/* The element block the 3D step reads its element data in (Body lays them out so). */
int block_size(void) { return B; }



/* The elastic forces of elements [e0, e1) into f, in the step's precision. */
static int step_forces(const Step *s, double *f, int64_t e0, int64_t e1)
{
    return s->single ? element_forces_f32(s, f, e0, e1) : element_forces(s, f, e0, e1);
}

/* thrust along each patch's area-weighted normal. */
static void rotor_forces(const Step *s)
{
    const int64_t d = s->dim;
    const double *x = s->x;
    for (int64_t r = 0; r < s->n_rotors; r++)
        for (int64_t k = s->vert_ptr[r]; k < s->vert_ptr[r + 1]; k++)
            for (int64_t c = 0; c < d; c++) s->ext[d * s->verts[k] + c] = 0.0;
    for (int64_t r = 0; r < s->n_rotors; r++) {
        double n[3] = {0.0, 0.0, 0.0};
        for (int64_t k = s->face_ptr[r]; k < s->face_ptr[r + 1]; k++) {
            const int64_t *fc = s->faces + 3 * k;
            const double *a = x + d * fc[0], *b = x + d * fc[1];
            if (d == 3) {
                const double *c = x + 3 * fc[2];
                double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, w[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
                n[0] += u[1] * w[2] - u[2] * w[1]; n[1] += u[2] * w[0] - u[0] * w[2]; n[2] += u[0] * w[1] - u[1] * w[0];
            } else {  /* outward normal of a counter-clockwise boundary segment a->b */
                n[0] += b[1] - a[1]; n[1] -= b[0] - a[0];
            }
        }
        double inv = 1.0 / sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2] + 1e-300);
        for (int64_t c = 0; c < d; c++) s->dirs[d * r + c] = n[c] * inv;
        for (int64_t k = s->vert_ptr[r]; k < s->vert_ptr[r + 1]; k++)
            for (int64_t c = 0; c < d; c++)
                s->ext[d * s->verts[k] + c] += s->thrust[r] * s->weights[k] * n[c] * inv;
    }
}

/* The sums behind the deformation damping, over free vertices, relative to a reference point
 * (positions far from the origin would otherwise cancel): M, sum m r, sum m v, sum m r x v,
 * sum m r r^T (6: xx xy xz yy yz zz). */
enum { S_M, S_R, S_P = 4, S_L = 7, S_S = 10, S_LEN = 16, S_STRIDE = 24 };

/* The velocity of the rigid motion that carries the body's momenta, from the summed sums:
 * centre of mass c (relative to the reference), its velocity p, the angular velocity w. */
static void rigid_motion(const double *sum, int64_t dim, double c[3], double p[3], double w[3])
{
    double M = sum[S_M];
    for (int a = 0; a < 3; a++) { c[a] = sum[S_R + a] / M; p[a] = sum[S_P + a] / M; w[a] = 0.0; }
    /* about the centre of mass: L = sum m r x v - M c x p, S = sum m r r^T - M c c^T */
    double L[3] = {sum[S_L] - M * (c[1] * p[2] - c[2] * p[1]), sum[S_L + 1] - M * (c[2] * p[0] - c[0] * p[2]),
                   sum[S_L + 2] - M * (c[0] * p[1] - c[1] * p[0])};
    double sxx = sum[S_S] - M * c[0] * c[0], sxy = sum[S_S + 1] - M * c[0] * c[1], sxz = sum[S_S + 2] - M * c[0] * c[2];
    double syy = sum[S_S + 3] - M * c[1] * c[1], syz = sum[S_S + 4] - M * c[1] * c[2], szz = sum[S_S + 5] - M * c[2] * c[2];
    if (dim == 2) { w[2] = L[2] / (sxx + syy); return; }
    /* inertia I = tr(S) 1 - S, symmetric; w = I^-1 L by the adjugate */
    double a = syy + szz, b = -sxy, cc = -sxz, d = sxx + szz, e = -syz, f = sxx + syy;
    double A00 = d * f - e * e, A01 = cc * e - b * f, A02 = b * e - cc * d;
    double A11 = a * f - cc * cc, A12 = b * cc - a * e, A22 = a * d - b * b;
    double inv = 1.0 / (a * A00 + b * A01 + cc * A02);
    w[0] = inv * (A00 * L[0] + A01 * L[1] + A02 * L[2]);
    w[1] = inv * (A01 * L[0] + A11 * L[1] + A12 * L[2]);
    w[2] = inv * (A02 * L[0] + A12 * L[1] + A22 * L[2]);
}

#if defined(__FMA__) && (defined(__x86_64__) || defined(__i386__))
#define EXACT_SIMD 1
#ifdef __AVX512F__
#define KEEP(a) __asm__("" : "+v"(a))   /* an opaque step: no vectorising, no reassociating the sum */
#else
#define KEEP(a) __asm__("" : "+x"(a))
#endif
#else
#define EXACT_SIMD 0
#endif

/* Contact of one vertex (position p, velocity u) with the ground and the static boxes: project
 * out along the normal, cancel the inward normal velocity, take Coulomb friction off the
 * tangential velocity. */
static inline __attribute__((always_inline)) void contact(const Step *restrict s, const int d,
        double *restrict p, double *restrict u)
{
    if (p[1] < s->ground) {
        p[1] = s->ground;
        if (u[1] < 0.0) {
#if EXACT_SIMD   /* the sums of squares as gcc had contracted them before the SIMD loops (see kick_impl) */
            double vt = sqrt(d == 3 ? fma(u[2], u[2], u[0] * u[0]) : u[0] * u[0]);
#else
            double vt = sqrt(u[0] * u[0] + u[2] * u[2]);
#endif
            double keep = fmax(0.0, 1.0 - s->friction * (-u[1]) / (vt + 1e-12));
            u[0] *= keep; u[2] *= keep; u[1] = 0.0;
        }
    }
    for (int64_t b = 0; b < s->n_boxes; b++) {
        const double *lo = s->boxes_min + d * b, *hi = s->boxes_max + d * b;
        int inside = 1;
        for (int c = 0; c < d; c++) inside &= p[c] > lo[c] && p[c] < hi[c];
        if (!inside) continue;
        double best = 1e300, side = 0.0;
        int axis = 0;
        for (int c = 0; c < d; c++) {
            if (p[c] - lo[c] < best) { best = p[c] - lo[c]; axis = c; side = -1.0; }
            if (hi[c] - p[c] < best) { best = hi[c] - p[c]; axis = c; side = 1.0; }
        }
        double vn = u[axis];
        p[axis] += side * best;
        if (vn * side < 0.0) {
#if EXACT_SIMD
            double t2 = d == 3 ? fma(u[2], u[2], u[1] * u[1]) + fma(-vn, vn, u[0] * u[0])
                               : fma(u[1], u[1], u[0] * u[0]) + fma(-vn, vn, u[2] * u[2]);
#else
            double t2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2] - vn * vn;
#endif
            double keep = fmax(0.0, 1.0 - s->friction * fabs(vn) / (sqrt(fmax(t2, 0.0)) + 1e-12));
            u[0] *= keep; u[1] *= keep; u[2] *= keep;
            u[axis] = 0.0;
        }
    }
}

/* The vertex loops (kick, drift) are bitwise those of the scalar loops they replaced (issue 25;
 * the scalar loop is kept below as kick_scalar and drift's contact loop): every result is
 * expected to repeat to the digit, and a chaotic flight amplifies one ulp. Under -ffast-math gcc
 * had contracted and reassociated those scalar loops in its own way (read from
 * -fdump-tree-optimized, gcc 12, x86-64 with FMA); the SIMD loops spell out the same expression
 * trees with explicit fma(), one rounding where the scalar code had one, and add the
 * deformation-damping sums vertex by vertex in the scalar order. tests/sim/test_bitwise_step.py steps this
 * code against the base commit's build (bitwise, both precisions, 1 and 2 threads, contacts).
 * Without FMA (where gcc contracts nothing) the scalar loops run as before. The sums over thread
 * buffers are in thread order, as the scalar loop's for up to 3 threads (gcc vectorised that
 * loop, reassociating it, from 4). */

/* The old scalar velocity update (the fallback without FMA; kick_impl is bitwise this with it). */
static inline __attribute__((always_inline)) void kick_scalar(const Step *restrict s, const int d,
        int64_t v0, int64_t v1, double scale, const double *restrict ref, double *restrict my)
{
    const int64_t nv = s->nv, nt = s->nt;
    const double dt = s->dt, grav = s->gravity;
    const double *restrict ext = s->ext, *restrict fext = s->fext, *restrict fb = s->fbuf;
    const double *restrict minv = s->minv, *restrict mass = s->mass, *restrict x = s->x;
    const double *restrict gshare = s->gravity_share;
    double *restrict v = s->v;
    const int sums = s->deform_damping > 0.0;
    double M = 0, rx = 0, ry = 0, rz = 0, px = 0, py = 0, pz = 0, lx = 0, ly = 0, lz = 0;
    double sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    for (int64_t i = v0; i < v1; i++) {
        double fx = ext[d * i] + fext[d * i], fy = ext[d * i + 1] + fext[d * i + 1], fz = 0.0;
        if (d == 3) fz = ext[d * i + 2] + fext[d * i + 2];
        for (int64_t k = 0; k < nt; k++) {
            const double *g = fb + d * (nv * k + i);
            fx += g[0]; fy += g[1];
            if (d == 3) fz += g[2];
        }
        double mi = minv[i], g = mi > 0.0 ? (gshare ? grav * gshare[i] : grav) : 0.0;
        double ux = (v[d * i] + dt * fx * mi) * scale, uy = (v[d * i + 1] + dt * (fy * mi - g)) * scale, uz = 0.0;
        v[d * i] = ux; v[d * i + 1] = uy;
        if (d == 3) { uz = (v[d * i + 2] + dt * fz * mi) * scale; v[d * i + 2] = uz; }
        if (sums && mi != 0.0) {
            double m = mass[i], ax = x[d * i] - ref[0], ay = x[d * i + 1] - ref[1], az = 0.0;
            if (d == 3) az = x[d * i + 2] - ref[2];
            M += m; rx += m * ax; ry += m * ay; rz += m * az; px += m * ux; py += m * uy; pz += m * uz;
            lx += m * (ay * uz - az * uy); ly += m * (az * ux - ax * uz); lz += m * (ax * uy - ay * ux);
            sxx += m * ax * ax; sxy += m * ax * ay; sxz += m * ax * az;
            syy += m * ay * ay; syz += m * ay * az; szz += m * az * az;
        }
    }
    my[S_M] = M; my[S_R] = rx; my[S_R + 1] = ry; my[S_R + 2] = rz; my[S_P] = px; my[S_P + 1] = py; my[S_P + 2] = pz;
    my[S_L] = lx; my[S_L + 1] = ly; my[S_L + 2] = lz;
    my[S_S] = sxx; my[S_S + 1] = sxy; my[S_S + 2] = sxz; my[S_S + 3] = syy; my[S_S + 4] = syz; my[S_S + 5] = szz;
}

#if EXACT_SIMD
/* The summed forces (elastic, rotor, effects) on vertices [i0, i0 + n) into F: ext + fext, then
 * the elastic forces of each thread's buffer fbuf[t] in turn. */
static inline __attribute__((always_inline)) void tile_forces(const Step *restrict s, const int d,
        int64_t i0, int n, double (*restrict F)[VT])
{
    const int64_t nv = s->nv, nt = s->nt;
    const double *restrict ext = s->ext, *restrict fext = s->fext, *restrict fb = s->fbuf;
    #pragma omp simd
    for (int j = 0; j < n; j++) {
        const int64_t i = i0 + j;
        F[0][j] = ext[d * i] + fext[d * i]; F[1][j] = ext[d * i + 1] + fext[d * i + 1];
        F[2][j] = d == 3 ? ext[d * i + 2] + fext[d * i + 2] : 0.0;
    }
    for (int64_t k = 0; k < nt; k++) {
        const double *restrict g = fb + d * (nv * k + i0);
        #pragma omp simd
        for (int j = 0; j < n; j++) {
            F[0][j] += g[d * j]; F[1][j] += g[d * j + 1];
            if (d == 3) F[2][j] += g[d * j + 2];
        }
    }
}

/* Velocity update of vertices [v0, v1): all forces, gravity, damping of the absolute velocity;
 * adds their deformation-damping sums (relative to ref) into my. In tiles of VT vertices: their
 * forces summed first (tile_forces), then one SIMD loop for the velocities and the terms of the
 * sums, then the sums in vertex order (scalar: sixteen independent chains). d and sums are
 * literals at each call, so the compiler drops the z arithmetic in 2D and the sums when there
 * is no deformation damping. The expressions are kick_scalar's as gcc compiled them:
 * u = scale (v + f (mi dt)) fused, uy's (fy mi - g) fused and then dt that + v fused;
 * r += m a unfused, p += u m fused, l += m (one product fused, the other rounded), s += a (m a). */
static inline __attribute__((always_inline)) void kick_impl(const Step *restrict s, const int d, const int sums,
        int64_t v0, int64_t v1, double scale, const double *restrict ref, double *restrict my)
{
    const double dt = s->dt, grav = s->gravity;
    const double *restrict minv = s->minv, *restrict mass = s->mass, *restrict x = s->x;
    const double *restrict gshare = s->gravity_share;
    double *restrict v = s->v;
    const double r0 = ref[0], r1 = ref[1], r2 = ref[2];
    double M = 0, rx = 0, ry = 0, rz = 0, px = 0, py = 0, pz = 0, lx = 0, ly = 0, lz = 0;
    double sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    double F[3][VT];
    /* per vertex of the tile: m (0 when pinned), m a, u, the cross terms of a x u, a */
    double Tm[VT], Tma[3][VT], Tu[3][VT], Tl[3][VT], Ta[3][VT];
    for (int64_t i0 = v0; i0 < v1; i0 += VT) {
        const int n = v1 - i0 < VT ? (int)(v1 - i0) : VT;
        tile_forces(s, d, i0, n, F);
        #pragma omp simd
        for (int j = 0; j < n; j++) {
            const int64_t i = i0 + j;
            const double mi = minv[i], g = mi > 0.0 ? (gshare ? grav * gshare[i] : grav) : 0.0, mdt = mi * dt;
            const double ux = scale * fma(F[0][j], mdt, v[d * i]);
            const double uy = scale * fma(fma(F[1][j], mi, -g), dt, v[d * i + 1]);
            v[d * i] = ux; v[d * i + 1] = uy;
            double uz = 0.0;
            if (d == 3) { uz = scale * fma(F[2][j], mdt, v[d * i + 2]); v[d * i + 2] = uz; }
            if (sums) {   /* pinned vertices (minv 0) count with no mass: each sum gains an exact 0 */
                const double m = mi != 0.0 ? mass[i] : 0.0, ax = x[d * i] - r0, ay = x[d * i + 1] - r1;
                Tm[j] = m; Tma[0][j] = m * ax; Tma[1][j] = m * ay; Ta[0][j] = ax; Ta[1][j] = ay;
                Tu[0][j] = ux; Tu[1][j] = uy;
                Tl[2][j] = fma(uy, ax, -(ux * ay));
                if (d == 3) {
                    const double az = x[d * i + 2] - r2;
                    Tma[2][j] = m * az; Ta[2][j] = az; Tu[2][j] = uz;
                    Tl[0][j] = fma(uz, ay, -(uy * az)); Tl[1][j] = fma(ux, az, -(uz * ax));
                }
            }
        }
        if (sums)
            for (int j = 0; j < n; j++) {
                const double m = Tm[j], mx = Tma[0][j], mY = Tma[1][j], ax = Ta[0][j], ay = Ta[1][j];
                M += m; rx += mx; ry += mY;
                px = fma(Tu[0][j], m, px); py = fma(Tu[1][j], m, py); lz = fma(m, Tl[2][j], lz);
                sxx = fma(ax, mx, sxx); sxy = fma(ay, mx, sxy); syy = fma(ay, mY, syy);
                KEEP(M); KEEP(rx); KEEP(ry); KEEP(px); KEEP(py); KEEP(lz); KEEP(sxx); KEEP(sxy); KEEP(syy);
                if (d == 3) {
                    const double mz = Tma[2][j], az = Ta[2][j];
                    rz += mz; pz = fma(Tu[2][j], m, pz); lx = fma(m, Tl[0][j], lx); ly = fma(m, Tl[1][j], ly);
                    sxz = fma(az, mx, sxz); syz = fma(az, mY, syz); szz = fma(az, mz, szz);
                    KEEP(rz); KEEP(pz); KEEP(lx); KEEP(ly); KEEP(sxz); KEEP(syz); KEEP(szz);
                }
            }
    }
    my[S_M] = M; my[S_R] = rx; my[S_R + 1] = ry; my[S_R + 2] = rz; my[S_P] = px; my[S_P + 1] = py; my[S_P + 2] = pz;
    my[S_L] = lx; my[S_L + 1] = ly; my[S_L + 2] = lz;
    my[S_S] = sxx; my[S_S + 1] = sxy; my[S_S + 2] = sxz; my[S_S + 3] = syy; my[S_S + 4] = syz; my[S_S + 5] = szz;
}
#endif

static inline __attribute__((always_inline)) void kick(const Step *restrict s, const int d,
        int64_t v0, int64_t v1, double scale, const double *restrict ref, double *restrict my)
{
#if EXACT_SIMD
    if (s->deform_damping > 0.0) kick_impl(s, d, 1, v0, v1, scale, ref, my);
    else kick_impl(s, d, 0, v0, v1, scale, ref, my);
#else
    kick_scalar(s, d, v0, v1, scale, ref, my);
#endif
}

#if EXACT_SIMD
/* drift's arithmetic for one vertex before its contacts, as gcc had compiled the scalar loop:
 * the deformation damping u' = g + keep (u - g), g = p + w x a (a = q - (ref + c)), spelled
 * (3D) g = (p + w a) - w a and u - g = (u + w a) - (p + w a), each + or - of a product fused;
 * (2D) ux - gx = (ux - px) + w ay; then q += dt u fused. on: the vertex is free. */
static inline __attribute__((always_inline)) void damp_move(const int d, const int damp, const int on,
        const double *restrict rc, const double *restrict p, const double *restrict w, double keep, double dt,
        double *restrict u, double *restrict q)
{
    double ux = u[0], uy = u[1], uz = u[2];
    if (damp) {
        const double ax = q[0] - rc[0], ay = q[1] - rc[1];
        if (d == 3) {
            const double az = q[2] - rc[2];
            const double tx = fma(az, w[1], p[0]), gx = fma(-ay, w[2], tx);
            const double ty = fma(ax, w[2], p[1]), gy = fma(-az, w[0], ty);
            const double tz = fma(ay, w[0], p[2]), gz = fma(-ax, w[1], tz);
            const double nx = fma(keep, fma(ay, w[2], ux) - tx, gx);
            const double ny = fma(keep, fma(az, w[0], uy) - ty, gy);
            const double nz = fma(keep, fma(ax, w[1], uz) - tz, gz);
            ux = on ? nx : ux; uy = on ? ny : uy; uz = on ? nz : uz;
        } else {
            const double gx = fma(-ay, w[2], p[0]), gy = fma(ax, w[2], p[1]);
            const double nx = fma(keep, fma(ay, w[2], ux - p[0]), gx);
            const double ny = fma(uy - gy, keep, gy);
            ux = on ? nx : ux; uy = on ? ny : uy;
        }
    }
    u[0] = ux; u[1] = uy; u[2] = uz;
    q[0] = fma(dt, ux, q[0]); q[1] = fma(dt, uy, q[1]);
    if (d == 3) q[2] = fma(dt, uz, q[2]);
}

/* |u|^2 as the scalar loop had it: 3D (ux ux + uz uz fused) + uy uy rounded. The max with
 * uy uy changes nothing (the first term is >= 0) but gives the product a use gcc cannot fuse
 * into the addition, so it stays rounded as before. */
static inline __attribute__((always_inline)) double speed2(const int d, const double *restrict u)
{
    if (d == 3) {
        const double yy = u[1] * u[1];
        return fmax(fma(u[0], u[0], u[2] * u[2]) + yy, yy);
    }
    return fma(u[0], u[0], u[1] * u[1]);
}
#endif

/* Deformation damping (keep < 1 when damp) towards the rigid velocity p + w x (x - ref - c),
 * position update and contact of vertices [v0, v1). Returns their largest squared speed.
 * Without contacts one SIMD loop (branch-free), with them a scalar loop; both bitwise the
 * scalar loop of before (damp_move). */
static inline __attribute__((always_inline)) double drift(const Step *restrict s, const int d,
        int64_t v0, int64_t v1, int damp, double keep, const double *restrict ref,
        const double *restrict c, const double *restrict p, const double *restrict w)
{
    const double dt = s->dt;
    const double *restrict minv = s->minv;
    double *restrict x = s->x, *restrict v = s->v;
    const int contacts = s->ground > -1e300 || s->n_boxes > 0;  /* Body passes -1e300 for none */
    double vmax = 0.0;
#if EXACT_SIMD
    const double rc[3] = {ref[0] + c[0], ref[1] + c[1], ref[2] + c[2]};
    const double pp[3] = {p[0], p[1], p[2]}, ww[3] = {w[0], w[1], w[2]};
    if (!contacts) {
        #pragma omp simd reduction(max:vmax)
        for (int64_t i = v0; i < v1; i++) {
            double u[3] = {v[d * i], v[d * i + 1], d == 3 ? v[d * i + 2] : 0.0};
            double q[3] = {x[d * i], x[d * i + 1], d == 3 ? x[d * i + 2] : 0.0};
            damp_move(d, damp, minv[i] != 0.0, rc, pp, ww, keep, dt, u, q);
            x[d * i] = q[0]; x[d * i + 1] = q[1]; v[d * i] = u[0]; v[d * i + 1] = u[1];
            if (d == 3) { x[d * i + 2] = q[2]; v[d * i + 2] = u[2]; }
            const double sp = speed2(d, u);
            vmax = sp > vmax ? sp : vmax;
        }
    } else
        for (int64_t i = v0; i < v1; i++) {
            double u[3] = {v[d * i], v[d * i + 1], d == 3 ? v[d * i + 2] : 0.0};
            double q[3] = {x[d * i], x[d * i + 1], d == 3 ? x[d * i + 2] : 0.0};
            damp_move(d, damp, minv[i] != 0.0, rc, pp, ww, keep, dt, u, q);
            contact(s, d, q, u);
            x[d * i] = q[0]; x[d * i + 1] = q[1]; v[d * i] = u[0]; v[d * i + 1] = u[1];
            if (d == 3) { x[d * i + 2] = q[2]; v[d * i + 2] = u[2]; }
            const double sp = speed2(d, u);
            vmax = sp > vmax ? sp : vmax;
        }
#else
    for (int64_t i = v0; i < v1; i++) {
        double ux = v[d * i], uy = v[d * i + 1], uz = d == 3 ? v[d * i + 2] : 0.0;
        double qx = x[d * i], qy = x[d * i + 1], qz = d == 3 ? x[d * i + 2] : 0.0;
        if (damp && minv[i] != 0.0) {
            double ax = qx - ref[0] - c[0], ay = qy - ref[1] - c[1], az = d == 3 ? qz - ref[2] - c[2] : 0.0;
            double gx = p[0] + w[1] * az - w[2] * ay, gy = p[1] + w[2] * ax - w[0] * az;
            ux = gx + keep * (ux - gx); uy = gy + keep * (uy - gy);
            if (d == 3) { double gz = p[2] + w[0] * ay - w[1] * ax; uz = gz + keep * (uz - gz); }
        }
        qx += dt * ux; qy += dt * uy; qz += dt * uz;
        if (contacts) {
            double pp[3] = {qx, qy, qz}, uu[3] = {ux, uy, uz};
            contact(s, d, pp, uu);
            qx = pp[0]; qy = pp[1]; qz = pp[2]; ux = uu[0]; uy = uu[1]; uz = uu[2];
        }
        x[d * i] = qx; x[d * i + 1] = qy; v[d * i] = ux; v[d * i + 1] = uy;
        if (d == 3) { x[d * i + 2] = qz; v[d * i + 2] = uz; }
        double sp = ux * ux + uy * uy + uz * uz;
        vmax = sp > vmax ? sp : vmax;
    }
#endif
    return vmax;
}

/* n_sub substeps (reference.advance) in one OpenMP region: per substep, thread t adds the
 * forces of element chunk t into fbuf[t] (thread 0 also the rotors'), then updates the
 * velocities of vertex chunk t and its share of the damping sums, then damps and moves them.
 * Three barriers a substep instead of a parallel region plus a serial pass.
 * Returns the most inverted elements seen in one substep; *vmax2 gets the largest squared
 * speed; -1 when out of memory. */
int advance(const Step *s, double *vmax2)
{
    const int64_t d = s->dim, nv = s->nv, nt = s->nt;
    double *sums = calloc((size_t)(nt * S_STRIDE), sizeof(double));
    int *inv = calloc((size_t)nt, sizeof(int));
    if (!sums || !inv) { free(sums); free(inv); return -1; }
    int worst = 0;
    double vmax = 0.0;
    const double scale = 1.0 / (1.0 + s->dt * s->damping);
    const double keep = 1.0 / (1.0 + s->dt * s->deform_damping);
    #pragma omp parallel num_threads(nt) reduction(max:vmax)
    {
        const int64_t t = omp_get_thread_num();
        /* 3D: whole blocks per thread (the element data is blocked, see forces_impl) */
        const int64_t ec = d == 3 ? ((s->ne + B - 1) / B + nt - 1) / nt * B : (s->ne + nt - 1) / nt;
        const int64_t e0 = t * ec, e1 = e0 + ec < s->ne ? e0 + ec : s->ne;
        const int64_t vc = (nv + nt - 1) / nt, v0 = t * vc, v1 = v0 + vc < nv ? v0 + vc : nv;
        double *f = s->fbuf + d * nv * t, *my = sums + S_STRIDE * t;
        for (int64_t sub = 0; sub < s->n_sub; sub++) {
            memset(f, 0, (size_t)(d * nv) * sizeof(double));
            inv[t] = e0 >= e1 ? 0 : step_forces(s, f, e0, e1);
            if (t == 0) rotor_forces(s);
            #pragma omp barrier
            if (t == 0) {
                int total = 0;
                for (int64_t k = 0; k < nt; k++) total += inv[k];
                worst = total > worst ? total : worst;
            }
            /* sums relative to a vertex, not the origin: far from it they would cancel */
            const double ref[3] = {s->x[0], s->x[1], d == 3 ? s->x[2] : 0.0};
            if (d == 3) kick(s, 3, v0, v1, scale, ref, my);
            else kick(s, 2, v0, v1, scale, ref, my);
            #pragma omp barrier
            double c[3] = {0.0, 0.0, 0.0}, p[3] = {0.0, 0.0, 0.0}, w[3] = {0.0, 0.0, 0.0};
            int damp = 0;
            if (s->deform_damping > 0.0) {
                double total[S_LEN] = {0.0};
                for (int64_t k = 0; k < nt; k++)
                    for (int j = 0; j < S_LEN; j++) total[j] += sums[S_STRIDE * k + j];
                damp = total[S_M] > 0.0;
                if (damp) rigid_motion(total, d, c, p, w);
            }
            double sp = d == 3 ? drift(s, 3, v0, v1, damp, keep, ref, c, p, w)
                               : drift(s, 2, v0, v1, damp, keep, ref, c, p, w);
            vmax = sp > vmax ? sp : vmax;
            #pragma omp barrier
        }
    }
    free(sums); free(inv);
    *vmax2 = vmax;
    return worst;
}

/* For the benchmark (bench_sim): the element forces alone, reps times, on one thread into
 * fbuf[0] (zeroed each time, as in a substep). Returns the inverted count of the last. */
int forces_only(const Step *s, int64_t reps)
{
    int inverted = 0;
    for (int64_t r = 0; r < reps; r++) {
        memset(s->fbuf, 0, (size_t)(s->dim * s->nv) * sizeof(double));
        inverted = step_forces(s, s->fbuf, 0, s->ne);
    }
    return inverted;
}

/* The peak probe (bench_sim): n rounds of multiply-adds a = a b + c on 16 registers' worth of
 * independent accumulators (16 x 64 bytes: enough chains to hide the FMA latency on both FMA
 * ports, few enough to stay in registers), 2 flops each, in double or float, compiled with the
 * kernels' flags: what a perfectly vectorised loop reaches on this core with this compiler. */
#define PROBE(NAME_, T) \
double NAME_(int64_t n, double seed) \
{ \
    enum { ACC = 16 * 64 / (int)sizeof(T) }; \
    T acc[ACC], b = (T)0.999999, c = (T)1e-7; \
    for (int k = 0; k < ACC; k++) acc[k] = (T)seed + (T)k * (T)1e-6; \
    for (int64_t i = 0; i < n; i++) { \
        _Pragma("omp simd") \
        for (int k = 0; k < ACC; k++) acc[k] = acc[k] * b + c; \
    } \
    double total = 0.0; \
    for (int k = 0; k < ACC; k++) total += acc[k]; \
    return total; \
}
PROBE(fma_probe, double)
PROBE(fma_probe_f32, float)

/* the accumulators per call of each probe: flops = 2 x this x n */
int fma_probe_width(int single) { return single ? 16 * 64 / (int)sizeof(float) : 16 * 64 / (int)sizeof(double); }
