/* The hot loops of sdexp's simulator: co-rotated linear element forces (see fem.py for the
 * math; fem.corotated_range_3d/_2d are the same computation in numba) and whole control steps
 * of substeps (advance; integrator.advance is its numba reference and fallback).
 *
 * Elements are processed in blocks of B: a scalar gather of the edge vectors Ds into
 * structure-of-arrays buffers, one branch-free loop the compiler turns into SIMD (F = Ds Dm^-1
 * onwards), a scalar scatter of the forces. This layout is what lets gcc vectorise it; numba's
 * LLVM keeps the same arithmetic scalar.
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
#define POLAR_ITERATIONS 2  /* as fem.POLAR_ITERATIONS */
/* POLAR_ITERATIONS warm-started polar iterations on F (scalars f00..f22), updating the
 * quaternion (qw, qx, qy, qz) in place (a macro: scalar locals keep the SIMD loops vectorised). */
#define POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz) \
    for (int it_ = 0; it_ < POLAR_ITERATIONS; it_++) { \
        double r00 = 1.0 - 2.0 * (qy * qy + qz * qz), r01 = 2.0 * (qx * qy - qw * qz), r02 = 2.0 * (qx * qz + qw * qy); \
        double r10 = 2.0 * (qx * qy + qw * qz), r11 = 1.0 - 2.0 * (qx * qx + qz * qz), r12 = 2.0 * (qy * qz - qw * qx); \
        double r20 = 2.0 * (qx * qz - qw * qy), r21 = 2.0 * (qy * qz + qw * qx), r22 = 1.0 - 2.0 * (qx * qx + qy * qy); \
        double wx = (r10 * f20 - r20 * f10) + (r11 * f21 - r21 * f11) + (r12 * f22 - r22 * f12); \
        double wy = (r20 * f00 - r00 * f20) + (r21 * f01 - r01 * f21) + (r22 * f02 - r02 * f22); \
        double wz = (r00 * f10 - r10 * f00) + (r01 * f11 - r11 * f01) + (r02 * f12 - r12 * f02); \
        double den = 0.5 / (fabs(r00 * f00 + r10 * f10 + r20 * f20 + r01 * f01 + r11 * f11 + r21 * f21 + r02 * f02 + r12 * f12 + r22 * f22) + 1e-9); \
        double ax = wx * den, ay = wy * den, az = wz * den; \
        double nw = qw - ax * qx - ay * qy - az * qz, nx = qx + ax * qw + ay * qz - az * qy; \
        double ny = qy - ax * qz + ay * qw + az * qx, nz = qz + ax * qy - ay * qx + az * qw; \
        double inv = 1.0 / sqrt(nw * nw + nx * nx + ny * ny + nz * nz); \
        qw = nw * inv; qx = nx * inv; qy = ny * inv; qz = nz * inv; \
    }

/* Adds the nodal forces of elements [e0, e1) into f (nv, 3) and updates their warm-start
 * quaternions by POLAR_ITERATIONS polar iterations. Returns the inverted count.
 * Two layouts of the element data: rows (Bm (ne, 3, 3), vol (ne), q (ne, 4)), gathered into
 * the block's lanes first; or blocked (Bm (nb, 9, B), vol (nb, B), q (nb, 4, B), el padded to
 * nb B rows, e0 a multiple of B), read in place by the SIMD loop: no gather or scatter of q
 * (the flower's step ~20-40% faster, README Speed). The SIMD loop reads both through the same
 * [k B + i] pointers. */
static inline __attribute__((always_inline)) int forces_impl(const double *restrict x,
        const int32_t *restrict el, const double *restrict Bm, const double *restrict vol, double mu,
        double lam, double *restrict q, double *restrict f, int64_t e0, int64_t e1, const int blocked)
{
    int inverted = 0;
    double D[9][B], Q[4][B], M[9][B], V[B], H[9][B];
    for (int64_t base = e0; base < e1; base += B) {
        int n = (e1 - base) < B ? (int)(e1 - base) : B;
        const double *Mp = blocked ? Bm + 9 * base : &M[0][0], *Vp = blocked ? vol + base : V;
        double *Qp = blocked ? q + 4 * base : &Q[0][0];
        for (int i = 0; i < B; i++) {
            if (i >= n && !blocked) { for (int k = 0; k < 9; k++) D[k][i] = M[k][i] = 0.0;
                                      Q[0][i] = 1; Q[1][i] = Q[2][i] = Q[3][i] = 0; V[i] = 0; continue; }
            int64_t e = base + i;   /* blocked: rows past e1 are padding, vertex 0 four times */
            const int32_t *t = el + 4 * e;
            const double *p0 = x + 3 * t[0], *p1 = x + 3 * t[1], *p2 = x + 3 * t[2], *p3 = x + 3 * t[3];
            for (int c = 0; c < 3; c++) { D[3 * c][i] = p1[c] - p0[c]; D[3 * c + 1][i] = p2[c] - p0[c]; D[3 * c + 2][i] = p3[c] - p0[c]; }
            if (!blocked) {
                const double *b = Bm + 9 * e;
                for (int k = 0; k < 9; k++) M[k][i] = b[k];
                for (int k = 0; k < 4; k++) Q[k][i] = q[4 * e + k];
                V[i] = vol[e];
            }
        }
        #pragma omp simd reduction(+:inverted)
        for (int i = 0; i < B; i++) {
            double b00 = Mp[0 * B + i], b01 = Mp[1 * B + i], b02 = Mp[2 * B + i], b10 = Mp[3 * B + i], b11 = Mp[4 * B + i],
                   b12 = Mp[5 * B + i], b20 = Mp[6 * B + i], b21 = Mp[7 * B + i], b22 = Mp[8 * B + i];
            double d00 = D[0][i], d01 = D[1][i], d02 = D[2][i], d10 = D[3][i], d11 = D[4][i], d12 = D[5][i],
                   d20 = D[6][i], d21 = D[7][i], d22 = D[8][i];
            /* F = Ds Dm^-1 */
            double f00 = d00 * b00 + d01 * b10 + d02 * b20, f01 = d00 * b01 + d01 * b11 + d02 * b21, f02 = d00 * b02 + d01 * b12 + d02 * b22;
            double f10 = d10 * b00 + d11 * b10 + d12 * b20, f11 = d10 * b01 + d11 * b11 + d12 * b21, f12 = d10 * b02 + d11 * b12 + d12 * b22;
            double f20 = d20 * b00 + d21 * b10 + d22 * b20, f21 = d20 * b01 + d21 * b11 + d22 * b21, f22 = d20 * b02 + d21 * b12 + d22 * b22;
            double Vi = -Vp[i];
            double det = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20);
            inverted += (det <= 0.0) & (Vi != 0.0);  /* padding lanes have V = 0 */
            double qw = Qp[0 * B + i], qx = Qp[1 * B + i], qy = Qp[2 * B + i], qz = Qp[3 * B + i];
            POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz);
            Qp[0 * B + i] = qw; Qp[1 * B + i] = qx; Qp[2 * B + i] = qy; Qp[3 * B + i] = qz;
            double r00 = 1.0 - 2.0 * (qy * qy + qz * qz), r01 = 2.0 * (qx * qy - qw * qz), r02 = 2.0 * (qx * qz + qw * qy);
            double r10 = 2.0 * (qx * qy + qw * qz), r11 = 1.0 - 2.0 * (qx * qx + qz * qz), r12 = 2.0 * (qy * qz - qw * qx);
            double r20 = 2.0 * (qx * qz - qw * qy), r21 = 2.0 * (qy * qz + qw * qx), r22 = 1.0 - 2.0 * (qx * qx + qy * qy);
            double s00 = r00 * f00 + r10 * f10 + r20 * f20, s11 = r01 * f01 + r11 * f11 + r21 * f21, s22 = r02 * f02 + r12 * f12 + r22 * f22;
            double s01 = 0.5 * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20));
            double s02 = 0.5 * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20));
            double s12 = 0.5 * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21));
            double tr = lam * (s00 + s11 + s22 - 3.0), m2 = 2.0 * mu;
            double t00 = m2 * (s00 - 1.0) + tr, t11 = m2 * (s11 - 1.0) + tr, t22 = m2 * (s22 - 1.0) + tr;
            double t01 = m2 * s01, t02 = m2 * s02, t12 = m2 * s12;
            double p00 = Vi * (r00 * t00 + r01 * t01 + r02 * t02), p01 = Vi * (r00 * t01 + r01 * t11 + r02 * t12), p02 = Vi * (r00 * t02 + r01 * t12 + r02 * t22);
            double p10 = Vi * (r10 * t00 + r11 * t01 + r12 * t02), p11 = Vi * (r10 * t01 + r11 * t11 + r12 * t12), p12 = Vi * (r10 * t02 + r11 * t12 + r12 * t22);
            double p20 = Vi * (r20 * t00 + r21 * t01 + r22 * t02), p21 = Vi * (r20 * t01 + r21 * t11 + r22 * t12), p22 = Vi * (r20 * t02 + r21 * t12 + r22 * t22);
            H[0][i] = p00 * b00 + p01 * b01 + p02 * b02; H[1][i] = p10 * b00 + p11 * b01 + p12 * b02; H[2][i] = p20 * b00 + p21 * b01 + p22 * b02;
            H[3][i] = p00 * b10 + p01 * b11 + p02 * b12; H[4][i] = p10 * b10 + p11 * b11 + p12 * b12; H[5][i] = p20 * b10 + p21 * b11 + p22 * b12;
            H[6][i] = p00 * b20 + p01 * b21 + p02 * b22; H[7][i] = p10 * b20 + p11 * b21 + p12 * b22; H[8][i] = p20 * b20 + p21 * b21 + p22 * b22;
        }
        for (int i = 0; i < n; i++) {
            int64_t e = base + i;
            if (!blocked) for (int k = 0; k < 4; k++) q[4 * e + k] = Q[k][i];
            const int32_t *t = el + 4 * e;
            for (int c = 0; c < 3; c++) {
                double h0 = H[c][i], h1 = H[3 + c][i], h2 = H[6 + c][i];
                f[3 * t[1] + c] += h0; f[3 * t[2] + c] += h1; f[3 * t[3] + c] += h2;
                f[3 * t[0] + c] -= h0 + h1 + h2;
            }
        }
    }
    return inverted;
}

static int forces_range(const double *x, const int32_t *el, const double *Bm, const double *vol, double mu,
                        double lam, double *q, double *f, int64_t e0, int64_t e1)
{
    return forces_impl(x, el, Bm, vol, mu, lam, q, f, e0, e1, 0);
}

static int forces_blocked(const double *x, const int32_t *el, const double *Bm, const double *vol, double mu,
                          double lam, double *q, double *f, int64_t e0, int64_t e1)
{
    return forces_impl(x, el, Bm, vol, mu, lam, q, f, e0, e1, 1);
}

/* The element block the 3D step reads its element data in (Body lays them out so). */
int block_size(void) { return B; }

/* All ne elements in nt chunks, one per thread: thread t zeroes its own force buffer
 * fbuf[t] (nt, nv, 3) and adds its chunk's forces there, so no two threads write one vertex. */
int corotated_forces_3d(const double *x, const int32_t *el, const double *Bm, const double *vol,
                        double mu, double lam, double *q, double *fbuf, int64_t nv, int64_t ne,
                        int64_t nt)
{
    int inverted = 0;
    int64_t chunk = (ne + nt - 1) / nt;
    #pragma omp parallel for num_threads(nt) schedule(static) reduction(+:inverted)
    for (int64_t t = 0; t < nt; t++) {
        double *f = fbuf + 3 * nv * t;
        memset(f, 0, 3 * nv * sizeof(double));
        int64_t e0 = t * chunk, e1 = e0 + chunk < ne ? e0 + chunk : ne;
        if (e0 < e1)
            inverted += forces_range(x, el, Bm, vol, mu, lam, q, f, e0, e1);
    }
    return inverted;
}

/* ------------------------------------------------------------------------------------------
 * Quadratic elements (quadratic.py has the math and the numba reference p2_range_3d/_2d).
 * 10-node tets, VTK order: corners 0-3, edges 4 (0,1) 5 (1,2) 6 (0,2) 7 (0,3) 8 (1,3) 9 (2,3).
 * Blocked like forces_impl: el (nb B, 10), Bm (nb, 9, B), vol (nb, B), q (nb, 16, B) holding
 * one warm-start quaternion per quadrature point (slot k at rows 4k..4k+3). */
#define QA 0.5854101966249685
#define QB 0.1381966011250105

/* One quadrature point (barycentric L0..L3, literals at each call so the compiler folds them)
 * of a block of B tets: F from the effective corner positions (D: node offsets from node 0),
 * the co-rotated stress with R from the polar iteration on this point's quaternions Q, its
 * nodal forces added into H. Scalars and [k][i] arrays only: a
 * private array inside an omp simd loop made the kernel 20x slower than this. */
static inline __attribute__((always_inline)) int p2_point(const double L0, const double L1, const double L2,
        const double L3, double (*restrict D)[B], const double *restrict Mp, const double *restrict Vp,
        double *restrict Q, double mu, double lam, double (*restrict H)[B])
{
    int bad = 0;
    #pragma omp simd reduction(+:bad)
    for (int i = 0; i < B; i++) {
        double b00 = Mp[0 * B + i], b01 = Mp[1 * B + i], b02 = Mp[2 * B + i], b10 = Mp[3 * B + i], b11 = Mp[4 * B + i],
               b12 = Mp[5 * B + i], b20 = Mp[6 * B + i], b21 = Mp[7 * B + i], b22 = Mp[8 * B + i];
        double e[3][3];  /* effective edge vectors: e[c][j] = component c of y_{j+1} - y_0 */
        for (int c = 0; c < 3; c++) {
            /* node a's offset is D[3 (a - 1) + c] */
            double d1 = D[c][i], d2 = D[3 + c][i], d3 = D[6 + c][i], d01 = D[9 + c][i], d12 = D[12 + c][i];
            double d02 = D[15 + c][i], d03 = D[18 + c][i], d13 = D[21 + c][i], d23 = D[24 + c][i];
            double y0 = 4.0 * (L1 * d01 + L2 * d02 + L3 * d03);
            e[c][0] = (4.0 * L1 - 1.0) * d1 + 4.0 * (L0 * d01 + L2 * d12 + L3 * d13) - y0;
            e[c][1] = (4.0 * L2 - 1.0) * d2 + 4.0 * (L0 * d02 + L1 * d12 + L3 * d23) - y0;
            e[c][2] = (4.0 * L3 - 1.0) * d3 + 4.0 * (L0 * d03 + L1 * d13 + L2 * d23) - y0;
        }
        double f00 = e[0][0] * b00 + e[0][1] * b10 + e[0][2] * b20, f01 = e[0][0] * b01 + e[0][1] * b11 + e[0][2] * b21, f02 = e[0][0] * b02 + e[0][1] * b12 + e[0][2] * b22;
        double f10 = e[1][0] * b00 + e[1][1] * b10 + e[1][2] * b20, f11 = e[1][0] * b01 + e[1][1] * b11 + e[1][2] * b21, f12 = e[1][0] * b02 + e[1][1] * b12 + e[1][2] * b22;
        double f20 = e[2][0] * b00 + e[2][1] * b10 + e[2][2] * b20, f21 = e[2][0] * b01 + e[2][1] * b11 + e[2][2] * b21, f22 = e[2][0] * b02 + e[2][1] * b12 + e[2][2] * b22;
        double Vi = -0.25 * Vp[i];
        double det = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20);
        bad += (det <= 0.0) & (Vi != 0.0);  /* padding lanes have V = 0 */
        double qw = Q[0 * B + i], qx = Q[1 * B + i], qy = Q[2 * B + i], qz = Q[3 * B + i];
        POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz);
        Q[0 * B + i] = qw; Q[1 * B + i] = qx; Q[2 * B + i] = qy; Q[3 * B + i] = qz;
        double r00 = 1.0 - 2.0 * (qy * qy + qz * qz), r01 = 2.0 * (qx * qy - qw * qz), r02 = 2.0 * (qx * qz + qw * qy);
        double r10 = 2.0 * (qx * qy + qw * qz), r11 = 1.0 - 2.0 * (qx * qx + qz * qz), r12 = 2.0 * (qy * qz - qw * qx);
        double r20 = 2.0 * (qx * qz - qw * qy), r21 = 2.0 * (qy * qz + qw * qx), r22 = 1.0 - 2.0 * (qx * qx + qy * qy);
        double s00 = r00 * f00 + r10 * f10 + r20 * f20, s11 = r01 * f01 + r11 * f11 + r21 * f21, s22 = r02 * f02 + r12 * f12 + r22 * f22;
        double s01 = 0.5 * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20));
        double s02 = 0.5 * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20));
        double s12 = 0.5 * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21));
        double tr = lam * (s00 + s11 + s22 - 3.0), m2 = 2.0 * mu;
        double t00 = m2 * (s00 - 1.0) + tr, t11 = m2 * (s11 - 1.0) + tr, t22 = m2 * (s22 - 1.0) + tr;
        double t01 = m2 * s01, t02 = m2 * s02, t12 = m2 * s12;
        double p[3][3] = {
            {Vi * (r00 * t00 + r01 * t01 + r02 * t02), Vi * (r00 * t01 + r01 * t11 + r02 * t12), Vi * (r00 * t02 + r01 * t12 + r02 * t22)},
            {Vi * (r10 * t00 + r11 * t01 + r12 * t02), Vi * (r10 * t01 + r11 * t11 + r12 * t12), Vi * (r10 * t02 + r11 * t12 + r12 * t22)},
            {Vi * (r20 * t00 + r21 * t01 + r22 * t02), Vi * (r20 * t01 + r21 * t11 + r22 * t12), Vi * (r20 * t02 + r21 * t12 + r22 * t22)}};
        /* g_j = P grad L_j: grad L_1..3 are the rows of Bm, grad L_0 their negative sum; corner j
         * gets (4 L_j - 1) g_j, edge (i, j) 4 (L_i g_j + L_j g_i); H row 3 a + c: node a, axis c */
        for (int c = 0; c < 3; c++) {
            double g1 = p[c][0] * b00 + p[c][1] * b01 + p[c][2] * b02;
            double g2 = p[c][0] * b10 + p[c][1] * b11 + p[c][2] * b12;
            double g3 = p[c][0] * b20 + p[c][1] * b21 + p[c][2] * b22;
            double g0 = -(g1 + g2 + g3);
            H[c][i] += (4.0 * L0 - 1.0) * g0; H[3 + c][i] += (4.0 * L1 - 1.0) * g1;
            H[6 + c][i] += (4.0 * L2 - 1.0) * g2; H[9 + c][i] += (4.0 * L3 - 1.0) * g3;
            H[12 + c][i] += 4.0 * (L0 * g1 + L1 * g0); H[15 + c][i] += 4.0 * (L1 * g2 + L2 * g1);
            H[18 + c][i] += 4.0 * (L0 * g2 + L2 * g0); H[21 + c][i] += 4.0 * (L0 * g3 + L3 * g0);
            H[24 + c][i] += 4.0 * (L1 * g3 + L3 * g1); H[27 + c][i] += 4.0 * (L2 * g3 + L3 * g2);
        }
    }
    return bad;
}

static int p2_forces_blocked(const double *restrict x, const int32_t *restrict el, const double *restrict Bm,
        const double *restrict vol, double mu, double lam, double *restrict q, double *restrict f,
        int64_t e0, int64_t e1)
{
    int inverted = 0;
    double D[27][B], H[30][B];
    for (int64_t base = e0; base < e1; base += B) {
        int n = (e1 - base) < B ? (int)(e1 - base) : B;
        const double *Mp = Bm + 9 * base, *Vp = vol + base;
        double *Qp = q + 16 * base;
        for (int i = 0; i < B; i++) {   /* rows past e1 are padding: node 0 ten times */
            const int32_t *t = el + 10 * (base + i);
            const double *p0 = x + 3 * t[0];
            for (int a = 1; a < 10; a++)
                for (int c = 0; c < 3; c++) D[3 * (a - 1) + c][i] = x[3 * t[a] + c] - p0[c];
        }
        memset(H, 0, sizeof(H));
        inverted += p2_point(QA, QB, QB, QB, D, Mp, Vp, Qp, mu, lam, H)
                  | p2_point(QB, QA, QB, QB, D, Mp, Vp, Qp + 4 * B, mu, lam, H)
                  | p2_point(QB, QB, QA, QB, D, Mp, Vp, Qp + 8 * B, mu, lam, H)
                  | p2_point(QB, QB, QB, QA, D, Mp, Vp, Qp + 12 * B, mu, lam, H);
        for (int i = 0; i < n; i++) {
            const int32_t *t = el + 10 * (base + i);
            for (int a = 0; a < 10; a++)
                for (int c = 0; c < 3; c++) f[3 * t[a] + c] += H[3 * a + c][i];
        }
    }
    return inverted;
}

/* 6-node triangles [e0, e1) into f (nv, 2), plane strain (quadratic.p2_range_2d): corners 0-2,
 * edges 3 (0,1) 4 (1,2) 5 (0,2); the exact 2D polar rotation at each of 3 quadrature points. */
static int p2_forces_range_2d(const double *restrict x, const int32_t *restrict el, const double *restrict Bm,
        const double *restrict vol, double mu, double lam, double *restrict f, int64_t e0, int64_t e1)
{
    static const double QL[3][3] = {{2.0 / 3, 1.0 / 6, 1.0 / 6}, {1.0 / 6, 2.0 / 3, 1.0 / 6}, {1.0 / 6, 1.0 / 6, 2.0 / 3}};
    static const int EI[3] = {0, 1, 0}, EJ[3] = {1, 2, 2};
    int inverted = 0;
    for (int64_t e = e0; e < e1; e++) {
        const int32_t *t = el + 6 * e;
        const double *bm = Bm + 4 * e;
        double b00 = bm[0], b01 = bm[1], b10 = bm[2], b11 = bm[3], V = -vol[e] / 3.0;
        double d[6][2], h[6][2] = {{0.0}};
        for (int a = 0; a < 6; a++) for (int c = 0; c < 2; c++) d[a][c] = x[2 * t[a] + c] - x[2 * t[0] + c];
        int bad = 0;
        for (int k = 0; k < 3; k++) {
            const double L[3] = {QL[k][0], QL[k][1], QL[k][2]};
            double e1v[2], e2v[2];
            for (int c = 0; c < 2; c++) {
                double y0 = 4.0 * (L[1] * d[3][c] + L[2] * d[5][c]);
                e1v[c] = (4.0 * L[1] - 1.0) * d[1][c] + 4.0 * (L[0] * d[3][c] + L[2] * d[4][c]) - y0;
                e2v[c] = (4.0 * L[2] - 1.0) * d[2][c] + 4.0 * (L[0] * d[5][c] + L[1] * d[4][c]) - y0;
            }
            double f00 = e1v[0] * b00 + e2v[0] * b10, f01 = e1v[0] * b01 + e2v[0] * b11;
            double f10 = e1v[1] * b00 + e2v[1] * b10, f11 = e1v[1] * b01 + e2v[1] * b11;
            bad |= f00 * f11 - f01 * f10 <= 0.0;
            double cs = f00 + f11, sn = f10 - f01;
            double inv_n = 1.0 / sqrt(cs * cs + sn * sn + 1e-300);
            cs *= inv_n; sn *= inv_n;
            double s00 = cs * f00 + sn * f10, s11 = -sn * f01 + cs * f11;
            double s01 = 0.5 * ((cs * f01 + sn * f11) + (-sn * f00 + cs * f10));
            double e00 = s00 - 1.0, e11 = s11 - 1.0, tr = lam * (e00 + e11);
            double t00 = 2.0 * mu * e00 + tr, t11 = 2.0 * mu * e11 + tr, t01 = 2.0 * mu * s01;
            double p00 = V * (cs * t00 - sn * t01), p01 = V * (cs * t01 - sn * t11);
            double p10 = V * (sn * t00 + cs * t01), p11 = V * (sn * t01 + cs * t11);
            double g[3][2];
            g[1][0] = p00 * b00 + p01 * b01; g[1][1] = p10 * b00 + p11 * b01;
            g[2][0] = p00 * b10 + p01 * b11; g[2][1] = p10 * b10 + p11 * b11;
            g[0][0] = -(g[1][0] + g[2][0]); g[0][1] = -(g[1][1] + g[2][1]);
            for (int j = 0; j < 3; j++) for (int c = 0; c < 2; c++) h[j][c] += (4.0 * L[j] - 1.0) * g[j][c];
            for (int m = 0; m < 3; m++)
                for (int c = 0; c < 2; c++) h[3 + m][c] += 4.0 * (L[EI[m]] * g[EJ[m]][c] + L[EJ[m]] * g[EI[m]][c]);
        }
        inverted += bad;
        for (int a = 0; a < 6; a++) for (int c = 0; c < 2; c++) f[2 * t[a] + c] += h[a][c];
    }
    return inverted;
}

/* Triangle forces of elements [e0, e1) into f (nv, 2), plane strain (fem.corotated_range_2d). */
static int forces_range_2d(const double *restrict x, const int32_t *restrict el, const double *restrict Bm,
        const double *restrict vol, double mu, double lam, double *restrict f, int64_t e0, int64_t e1)
{
    int inverted = 0;
    for (int64_t e = e0; e < e1; e++) {
        const int32_t *t = el + 3 * e;
        const double *b = Bm + 4 * e;
        double d1x = x[2 * t[1]] - x[2 * t[0]], d1y = x[2 * t[1] + 1] - x[2 * t[0] + 1];
        double d2x = x[2 * t[2]] - x[2 * t[0]], d2y = x[2 * t[2] + 1] - x[2 * t[0] + 1];
        double b00 = b[0], b01 = b[1], b10 = b[2], b11 = b[3];
        double f00 = d1x * b00 + d2x * b10, f01 = d1x * b01 + d2x * b11;
        double f10 = d1y * b00 + d2y * b10, f11 = d1y * b01 + d2y * b11;
        inverted += f00 * f11 - f01 * f10 <= 0.0;
        double c = f00 + f11, s = f10 - f01;   /* the exact polar rotation of a 2x2 F */
        double inv_n = 1.0 / sqrt(c * c + s * s + 1e-300);
        c *= inv_n; s *= inv_n;
        double s00 = c * f00 + s * f10, s11 = -s * f01 + c * f11;
        double s01 = 0.5 * ((c * f01 + s * f11) + (-s * f00 + c * f10));
        double e00 = s00 - 1.0, e11 = s11 - 1.0, tr = lam * (e00 + e11);
        double t00 = 2.0 * mu * e00 + tr, t11 = 2.0 * mu * e11 + tr, t01 = 2.0 * mu * s01, V = -vol[e];
        double p00 = V * (c * t00 - s * t01), p01 = V * (c * t01 - s * t11);
        double p10 = V * (s * t00 + c * t01), p11 = V * (s * t01 + c * t11);
        double h00 = p00 * b00 + p01 * b01, h10 = p10 * b00 + p11 * b01;
        double h01 = p00 * b10 + p01 * b11, h11 = p10 * b10 + p11 * b11;
        f[2 * t[1]] += h00; f[2 * t[1] + 1] += h10;
        f[2 * t[2]] += h01; f[2 * t[2] + 1] += h11;
        f[2 * t[0]] -= h00 + h01; f[2 * t[0] + 1] -= h10 + h11;
    }
    return inverted;
}

/* One body and one control step of it; native.Step mirrors this layout. Arrays are C-ordered
 * (rows: vertices or elements), dim = 2 or 3 columns; in 3D el, Bm, vol and q are blocked
 * (forces_impl, p2_forces_blocked). nodes: per element (4 / 3 linear, 10 / 6 quadratic). */
typedef struct {
    int64_t dim, nv, ne, nt, n_sub, n_rotors, n_boxes, nodes;
    double dt, mu, lam, damping, deform_damping, gravity, ground, friction;
    double *x, *v, *q, *fbuf, *ext, *dirs;
    const double *fext, *minv, *mass, *Bm, *vol, *boxes_min, *boxes_max, *weights, *thrust;
    const int32_t *el;
    const int64_t *face_ptr, *faces, *vert_ptr, *verts;
} Step;

/* integrator.rotor_forces: thrust along each patch's area-weighted normal. */
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

/* Contact of one vertex (position p, velocity u) with the ground and the static boxes: project
 * out along the normal, cancel the inward normal velocity, take Coulomb friction off the
 * tangential velocity (integrator.integrate). */
static inline __attribute__((always_inline)) void contact(const Step *restrict s, const int d,
        double *restrict p, double *restrict u)
{
    if (p[1] < s->ground) {
        p[1] = s->ground;
        if (u[1] < 0.0) {
            double vt = sqrt(u[0] * u[0] + u[2] * u[2]);
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
            double t2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2] - vn * vn;
            double keep = fmax(0.0, 1.0 - s->friction * fabs(vn) / (sqrt(fmax(t2, 0.0)) + 1e-12));
            u[0] *= keep; u[1] *= keep; u[2] *= keep;
            u[axis] = 0.0;
        }
    }
}

/* Velocity update of vertices [v0, v1): all forces, gravity, damping of the absolute velocity;
 * adds their deformation-damping sums (relative to ref) into my. d is a literal at each call,
 * so the compiler drops the z arithmetic in 2D. */
static inline __attribute__((always_inline)) void kick(const Step *restrict s, const int d,
        int64_t v0, int64_t v1, double scale, const double *restrict ref, double *restrict my)
{
    const int64_t nv = s->nv, nt = s->nt;
    const double dt = s->dt, grav = s->gravity;
    const double *restrict ext = s->ext, *restrict fext = s->fext, *restrict fb = s->fbuf;
    const double *restrict minv = s->minv, *restrict mass = s->mass, *restrict x = s->x;
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
        double mi = minv[i], g = mi > 0.0 ? grav : 0.0;
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

/* Deformation damping (keep < 1 when damp) towards the rigid velocity p + w x (x - ref - c),
 * position update and contact of vertices [v0, v1). Returns their largest squared speed. */
static inline __attribute__((always_inline)) double drift(const Step *restrict s, const int d,
        int64_t v0, int64_t v1, int damp, double keep, const double *restrict ref,
        const double *restrict c, const double *restrict p, const double *restrict w)
{
    const double dt = s->dt;
    const double *restrict minv = s->minv;
    double *restrict x = s->x, *restrict v = s->v;
    const int contacts = s->ground > -1e300 || s->n_boxes > 0;  /* Body passes -1e300 for none */
    double vmax = 0.0;
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
    return vmax;
}

/* n_sub substeps of integrator.advance in one OpenMP region: per substep, thread t adds the
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
            inv[t] = e0 >= e1 ? 0
                   : s->nodes == 10 ? p2_forces_blocked(s->x, s->el, s->Bm, s->vol, s->mu, s->lam, s->q, f, e0, e1)
                   : s->nodes == 6 ? p2_forces_range_2d(s->x, s->el, s->Bm, s->vol, s->mu, s->lam, f, e0, e1)
                   : d == 3 ? forces_blocked(s->x, s->el, s->Bm, s->vol, s->mu, s->lam, s->q, f, e0, e1)
                            : forces_range_2d(s->x, s->el, s->Bm, s->vol, s->mu, s->lam, f, e0, e1);
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
