/* The element force kernels of kernels.c, written once for a floating type: kernels.c includes
 * this file twice, with real = double (names as written) and real = float (names + _f32), so the
 * float32 forces of sim.precision are the same arithmetic with every operand in single precision.
 * Positions and the force buffers stay double: edge vectors are differences of double positions,
 * rounded to real only after the subtraction (a drone 3 m from the origin keeps a 0.1 m edge to
 * 1e-8 m, not 3e-7 m), and each element's nodal forces are added into double sums. Element data
 * (Bm, vol, q) are real arrays: half the bytes and twice the SIMD lanes in float.
 * Literals are R_(c) so that a float kernel never promotes to double (the 2D rotation's guard
 * against a zero length is 1e-30, not 1e-300, which is zero in float). */
#ifndef FORCES_H_SHARED
#define FORCES_H_SHARED
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define NAME(n) CAT(n, SUFFIX)
#define R_(c) ((real)(c))
/* POLAR_ITERATIONS warm-started polar iterations on F (scalars f00..f22), updating the
 * quaternion (qw, qx, qy, qz) in place (a macro: scalar locals keep the SIMD loops vectorised). */
#define POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz) \
    for (int it_ = 0; it_ < POLAR_ITERATIONS; it_++) { \
        real r00 = R_(1.0) - R_(2.0) * (qy * qy + qz * qz), r01 = R_(2.0) * (qx * qy - qw * qz), r02 = R_(2.0) * (qx * qz + qw * qy); \
        real r10 = R_(2.0) * (qx * qy + qw * qz), r11 = R_(1.0) - R_(2.0) * (qx * qx + qz * qz), r12 = R_(2.0) * (qy * qz - qw * qx); \
        real r20 = R_(2.0) * (qx * qz - qw * qy), r21 = R_(2.0) * (qy * qz + qw * qx), r22 = R_(1.0) - R_(2.0) * (qx * qx + qy * qy); \
        real wx = (r10 * f20 - r20 * f10) + (r11 * f21 - r21 * f11) + (r12 * f22 - r22 * f12); \
        real wy = (r20 * f00 - r00 * f20) + (r21 * f01 - r01 * f21) + (r22 * f02 - r02 * f22); \
        real wz = (r00 * f10 - r10 * f00) + (r01 * f11 - r11 * f01) + (r02 * f12 - r12 * f02); \
        real den = R_(0.5) / (RFABS(r00 * f00 + r10 * f10 + r20 * f20 + r01 * f01 + r11 * f11 + r21 * f21 + r02 * f02 + r12 * f12 + r22 * f22) + R_(1e-9)); \
        real ax = wx * den, ay = wy * den, az = wz * den; \
        real nw = qw - ax * qx - ay * qy - az * qz, nx = qx + ax * qw + ay * qz - az * qy; \
        real ny = qy - ax * qz + ay * qw + az * qx, nz = qz + ax * qy - ay * qx + az * qw; \
        real inv = R_(1.0) / RSQRT(nw * nw + nx * nx + ny * ny + nz * nz); \
        qw = nw * inv; qx = nx * inv; qy = ny * inv; qz = nz * inv; \
    }
#define QA 0.5854101966249685
#define QB 0.1381966011250105
#endif


/* Adds the nodal forces of elements [e0, e1) into f (nv, 3) and updates their warm-start
 * quaternions by POLAR_ITERATIONS polar iterations. Returns the inverted count.
 * Two layouts of the element data: rows (Bm (ne, 3, 3), vol (ne), q (ne, 4)), gathered into
 * the block's lanes first; or blocked (Bm (nb, 9, B), vol (nb, B), q (nb, 4, B), el padded to
 * nb B rows, e0 a multiple of B), read in place by the SIMD loop: no gather or scatter of q
 * (the flower's step ~20-40% faster, README Speed). The SIMD loop reads both through the same
 * [k B + i] pointers. */
static inline __attribute__((always_inline)) int NAME(forces_impl)(const double *restrict x,
        const int32_t *restrict el, const real *restrict Bm, const real *restrict vol, real mu,
        real lam, real *restrict q, double *restrict f, int64_t e0, int64_t e1, const int blocked)
{
    int inverted = 0;
    real D[9][B], Q[4][B], M[9][B], V[B], H[9][B];
    for (int64_t base = e0; base < e1; base += B) {
        int n = (e1 - base) < B ? (int)(e1 - base) : B;
        const real *Mp = blocked ? Bm + 9 * base : &M[0][0], *Vp = blocked ? vol + base : V;
        real *Qp = blocked ? q + 4 * base : &Q[0][0];
        for (int i = 0; i < B; i++) {
            if (i >= n && !blocked) { for (int k = 0; k < 9; k++) D[k][i] = M[k][i] = R_(0.0);
                                      Q[0][i] = 1; Q[1][i] = Q[2][i] = Q[3][i] = 0; V[i] = 0; continue; }
            int64_t e = base + i;   /* blocked: rows past e1 are padding, vertex 0 four times */
            const int32_t *t = el + 4 * e;
            const double *p0 = x + 3 * t[0], *p1 = x + 3 * t[1], *p2 = x + 3 * t[2], *p3 = x + 3 * t[3];
            for (int c = 0; c < 3; c++) { D[3 * c][i] = p1[c] - p0[c]; D[3 * c + 1][i] = p2[c] - p0[c]; D[3 * c + 2][i] = p3[c] - p0[c]; }
            if (!blocked) {
                const real *b = Bm + 9 * e;
                for (int k = 0; k < 9; k++) M[k][i] = b[k];
                for (int k = 0; k < 4; k++) Q[k][i] = q[4 * e + k];
                V[i] = vol[e];
            }
        }
        #pragma omp simd reduction(+:inverted)
        for (int i = 0; i < B; i++) {
            real b00 = Mp[0 * B + i], b01 = Mp[1 * B + i], b02 = Mp[2 * B + i], b10 = Mp[3 * B + i], b11 = Mp[4 * B + i],
                   b12 = Mp[5 * B + i], b20 = Mp[6 * B + i], b21 = Mp[7 * B + i], b22 = Mp[8 * B + i];
            real d00 = D[0][i], d01 = D[1][i], d02 = D[2][i], d10 = D[3][i], d11 = D[4][i], d12 = D[5][i],
                   d20 = D[6][i], d21 = D[7][i], d22 = D[8][i];
            /* F = Ds Dm^-1 */
            real f00 = d00 * b00 + d01 * b10 + d02 * b20, f01 = d00 * b01 + d01 * b11 + d02 * b21, f02 = d00 * b02 + d01 * b12 + d02 * b22;
            real f10 = d10 * b00 + d11 * b10 + d12 * b20, f11 = d10 * b01 + d11 * b11 + d12 * b21, f12 = d10 * b02 + d11 * b12 + d12 * b22;
            real f20 = d20 * b00 + d21 * b10 + d22 * b20, f21 = d20 * b01 + d21 * b11 + d22 * b21, f22 = d20 * b02 + d21 * b12 + d22 * b22;
            real Vi = -Vp[i];
            real det = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20);
            inverted += (det <= R_(0.0)) & (Vi != R_(0.0));  /* padding lanes have V = 0 */
            real qw = Qp[0 * B + i], qx = Qp[1 * B + i], qy = Qp[2 * B + i], qz = Qp[3 * B + i];
            POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz);
            Qp[0 * B + i] = qw; Qp[1 * B + i] = qx; Qp[2 * B + i] = qy; Qp[3 * B + i] = qz;
            real r00 = R_(1.0) - R_(2.0) * (qy * qy + qz * qz), r01 = R_(2.0) * (qx * qy - qw * qz), r02 = R_(2.0) * (qx * qz + qw * qy);
            real r10 = R_(2.0) * (qx * qy + qw * qz), r11 = R_(1.0) - R_(2.0) * (qx * qx + qz * qz), r12 = R_(2.0) * (qy * qz - qw * qx);
            real r20 = R_(2.0) * (qx * qz - qw * qy), r21 = R_(2.0) * (qy * qz + qw * qx), r22 = R_(1.0) - R_(2.0) * (qx * qx + qy * qy);
            real s00 = r00 * f00 + r10 * f10 + r20 * f20, s11 = r01 * f01 + r11 * f11 + r21 * f21, s22 = r02 * f02 + r12 * f12 + r22 * f22;
            real s01 = R_(0.5) * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20));
            real s02 = R_(0.5) * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20));
            real s12 = R_(0.5) * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21));
            real tr = lam * (s00 + s11 + s22 - R_(3.0)), m2 = R_(2.0) * mu;
            real t00 = m2 * (s00 - R_(1.0)) + tr, t11 = m2 * (s11 - R_(1.0)) + tr, t22 = m2 * (s22 - R_(1.0)) + tr;
            real t01 = m2 * s01, t02 = m2 * s02, t12 = m2 * s12;
            real p00 = Vi * (r00 * t00 + r01 * t01 + r02 * t02), p01 = Vi * (r00 * t01 + r01 * t11 + r02 * t12), p02 = Vi * (r00 * t02 + r01 * t12 + r02 * t22);
            real p10 = Vi * (r10 * t00 + r11 * t01 + r12 * t02), p11 = Vi * (r10 * t01 + r11 * t11 + r12 * t12), p12 = Vi * (r10 * t02 + r11 * t12 + r12 * t22);
            real p20 = Vi * (r20 * t00 + r21 * t01 + r22 * t02), p21 = Vi * (r20 * t01 + r21 * t11 + r22 * t12), p22 = Vi * (r20 * t02 + r21 * t12 + r22 * t22);
            H[0][i] = p00 * b00 + p01 * b01 + p02 * b02; H[1][i] = p10 * b00 + p11 * b01 + p12 * b02; H[2][i] = p20 * b00 + p21 * b01 + p22 * b02;
            H[3][i] = p00 * b10 + p01 * b11 + p02 * b12; H[4][i] = p10 * b10 + p11 * b11 + p12 * b12; H[5][i] = p20 * b10 + p21 * b11 + p22 * b12;
            H[6][i] = p00 * b20 + p01 * b21 + p02 * b22; H[7][i] = p10 * b20 + p11 * b21 + p12 * b22; H[8][i] = p20 * b20 + p21 * b21 + p22 * b22;
        }
        for (int i = 0; i < n; i++) {
            int64_t e = base + i;
            if (!blocked) for (int k = 0; k < 4; k++) q[4 * e + k] = Q[k][i];
            const int32_t *t = el + 4 * e;
            for (int c = 0; c < 3; c++) {
                real h0 = H[c][i], h1 = H[3 + c][i], h2 = H[6 + c][i];
                f[3 * t[1] + c] += h0; f[3 * t[2] + c] += h1; f[3 * t[3] + c] += h2;
                f[3 * t[0] + c] -= h0 + h1 + h2;
            }
        }
    }
    return inverted;
}

static int NAME(forces_range)(const double *x, const int32_t *el, const real *Bm, const real *vol, real mu,
                        real lam, real *q, double *f, int64_t e0, int64_t e1)
{
    return NAME(forces_impl)(x, el, Bm, vol, mu, lam, q, f, e0, e1, 0);
}

static int NAME(forces_blocked)(const double *x, const int32_t *el, const real *Bm, const real *vol, real mu,
                          real lam, real *q, double *f, int64_t e0, int64_t e1)
{
    return NAME(forces_impl)(x, el, Bm, vol, mu, lam, q, f, e0, e1, 1);
}

/* All ne elements in nt chunks, one per thread: thread t zeroes its own force buffer
 * fbuf[t] (nt, nv, 3) and adds its chunk's forces there, so no two threads write one vertex. */
int NAME(corotated_forces_3d)(const double *x, const int32_t *el, const real *Bm, const real *vol,
                        double mu, double lam, real *q, double *fbuf, int64_t nv, int64_t ne,
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
            inverted += NAME(forces_range)(x, el, Bm, vol, mu, lam, q, f, e0, e1);
    }
    return inverted;
}

/* ------------------------------------------------------------------------------------------
 * Quadratic elements (quadratic.py has the math; reference.py p2_forces_range and _2d in numba).
 * 10-node tets, VTK order: corners 0-3, edges 4 (0,1) 5 (1,2) 6 (0,2) 7 (0,3) 8 (1,3) 9 (2,3).
 * Blocked like forces_impl, el too: el (nb, 10, B), Bm (nb, 9, B), vol (nb, B), q (nb, 16, B) holding
 * one warm-start quaternion per quadrature point (slot k at rows 4k..4k+3). */
/* One quadrature point (barycentric L0..L3, literals at each call so the compiler folds them)
 * of a block of B tets: F from the effective corner positions (D: node offsets from node 0),
 * the co-rotated stress with R from the polar iteration on this point's quaternions Q, its
 * nodal forces added into H. Scalars and [k][i] arrays only: a
 * private array inside an omp simd loop made the kernel 20x slower than this. */
static inline __attribute__((always_inline)) int NAME(p2_point)(const real L0, const real L1, const real L2,
        const real L3, real (*restrict D)[B], const real *restrict Mp, const real *restrict Vp,
        real *restrict Q, real mu, real lam, real (*restrict H)[B])
{
    int bad = 0;
    #pragma omp simd reduction(+:bad)
    for (int i = 0; i < B; i++) {
        real b00 = Mp[0 * B + i], b01 = Mp[1 * B + i], b02 = Mp[2 * B + i], b10 = Mp[3 * B + i], b11 = Mp[4 * B + i],
               b12 = Mp[5 * B + i], b20 = Mp[6 * B + i], b21 = Mp[7 * B + i], b22 = Mp[8 * B + i];
        real e[3][3];  /* effective edge vectors: e[c][j] = component c of y_{j+1} - y_0 */
        for (int c = 0; c < 3; c++) {
            /* node a's offset is D[3 (a - 1) + c] */
            real d1 = D[c][i], d2 = D[3 + c][i], d3 = D[6 + c][i], d01 = D[9 + c][i], d12 = D[12 + c][i];
            real d02 = D[15 + c][i], d03 = D[18 + c][i], d13 = D[21 + c][i], d23 = D[24 + c][i];
            real y0 = R_(4.0) * (L1 * d01 + L2 * d02 + L3 * d03);
            e[c][0] = (R_(4.0) * L1 - R_(1.0)) * d1 + R_(4.0) * (L0 * d01 + L2 * d12 + L3 * d13) - y0;
            e[c][1] = (R_(4.0) * L2 - R_(1.0)) * d2 + R_(4.0) * (L0 * d02 + L1 * d12 + L3 * d23) - y0;
            e[c][2] = (R_(4.0) * L3 - R_(1.0)) * d3 + R_(4.0) * (L0 * d03 + L1 * d13 + L2 * d23) - y0;
        }
        real f00 = e[0][0] * b00 + e[0][1] * b10 + e[0][2] * b20, f01 = e[0][0] * b01 + e[0][1] * b11 + e[0][2] * b21, f02 = e[0][0] * b02 + e[0][1] * b12 + e[0][2] * b22;
        real f10 = e[1][0] * b00 + e[1][1] * b10 + e[1][2] * b20, f11 = e[1][0] * b01 + e[1][1] * b11 + e[1][2] * b21, f12 = e[1][0] * b02 + e[1][1] * b12 + e[1][2] * b22;
        real f20 = e[2][0] * b00 + e[2][1] * b10 + e[2][2] * b20, f21 = e[2][0] * b01 + e[2][1] * b11 + e[2][2] * b21, f22 = e[2][0] * b02 + e[2][1] * b12 + e[2][2] * b22;
        real Vi = -R_(0.25) * Vp[i];
        real det = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20);
        bad += (det <= R_(0.0)) & (Vi != R_(0.0));  /* padding lanes have V = 0 */
        real qw = Q[0 * B + i], qx = Q[1 * B + i], qy = Q[2 * B + i], qz = Q[3 * B + i];
        POLAR_ITERATE(f00, f01, f02, f10, f11, f12, f20, f21, f22, qw, qx, qy, qz);
        Q[0 * B + i] = qw; Q[1 * B + i] = qx; Q[2 * B + i] = qy; Q[3 * B + i] = qz;
        real r00 = R_(1.0) - R_(2.0) * (qy * qy + qz * qz), r01 = R_(2.0) * (qx * qy - qw * qz), r02 = R_(2.0) * (qx * qz + qw * qy);
        real r10 = R_(2.0) * (qx * qy + qw * qz), r11 = R_(1.0) - R_(2.0) * (qx * qx + qz * qz), r12 = R_(2.0) * (qy * qz - qw * qx);
        real r20 = R_(2.0) * (qx * qz - qw * qy), r21 = R_(2.0) * (qy * qz + qw * qx), r22 = R_(1.0) - R_(2.0) * (qx * qx + qy * qy);
        real s00 = r00 * f00 + r10 * f10 + r20 * f20, s11 = r01 * f01 + r11 * f11 + r21 * f21, s22 = r02 * f02 + r12 * f12 + r22 * f22;
        real s01 = R_(0.5) * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20));
        real s02 = R_(0.5) * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20));
        real s12 = R_(0.5) * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21));
        real tr = lam * (s00 + s11 + s22 - R_(3.0)), m2 = R_(2.0) * mu;
        real t00 = m2 * (s00 - R_(1.0)) + tr, t11 = m2 * (s11 - R_(1.0)) + tr, t22 = m2 * (s22 - R_(1.0)) + tr;
        real t01 = m2 * s01, t02 = m2 * s02, t12 = m2 * s12;
        real p[3][3] = {
            {Vi * (r00 * t00 + r01 * t01 + r02 * t02), Vi * (r00 * t01 + r01 * t11 + r02 * t12), Vi * (r00 * t02 + r01 * t12 + r02 * t22)},
            {Vi * (r10 * t00 + r11 * t01 + r12 * t02), Vi * (r10 * t01 + r11 * t11 + r12 * t12), Vi * (r10 * t02 + r11 * t12 + r12 * t22)},
            {Vi * (r20 * t00 + r21 * t01 + r22 * t02), Vi * (r20 * t01 + r21 * t11 + r22 * t12), Vi * (r20 * t02 + r21 * t12 + r22 * t22)}};
        /* g_j = P grad L_j: grad L_1..3 are the rows of Bm, grad L_0 their negative sum; corner j
         * gets (4 L_j - 1) g_j, edge (i, j) 4 (L_i g_j + L_j g_i); H row 3 a + c: node a, axis c */
        for (int c = 0; c < 3; c++) {
            real g1 = p[c][0] * b00 + p[c][1] * b01 + p[c][2] * b02;
            real g2 = p[c][0] * b10 + p[c][1] * b11 + p[c][2] * b12;
            real g3 = p[c][0] * b20 + p[c][1] * b21 + p[c][2] * b22;
            real g0 = -(g1 + g2 + g3);
            H[c][i] += (R_(4.0) * L0 - R_(1.0)) * g0; H[3 + c][i] += (R_(4.0) * L1 - R_(1.0)) * g1;
            H[6 + c][i] += (R_(4.0) * L2 - R_(1.0)) * g2; H[9 + c][i] += (R_(4.0) * L3 - R_(1.0)) * g3;
            H[12 + c][i] += R_(4.0) * (L0 * g1 + L1 * g0); H[15 + c][i] += R_(4.0) * (L1 * g2 + L2 * g1);
            H[18 + c][i] += R_(4.0) * (L0 * g2 + L2 * g0); H[21 + c][i] += R_(4.0) * (L0 * g3 + L3 * g0);
            H[24 + c][i] += R_(4.0) * (L1 * g3 + L3 * g1); H[27 + c][i] += R_(4.0) * (L2 * g3 + L3 * g2);
        }
    }
    return bad;
}

/* Quadratic tets [e0, e1) into f (nv, 3). el is (nb, 10, B), so the node offsets are read lane
 * by lane in SIMD gathers; the nodal forces are added into f by a scalar scatter, element by
 * element. (Measured against it on the flower, issue 25: a four-wide scatter into rows
 * (x, y, z, 0) after a SIMD transposition, and leaving the forces per element node for the
 * velocity update to sum per vertex, both no faster: docs/speed.md.) */
static int NAME(p2_forces_blocked)(const double *restrict x, const int32_t *restrict el, const real *restrict Bm,
        const real *restrict vol, real mu, real lam, real *restrict q, double *restrict f,
        int64_t e0, int64_t e1)
{
    int inverted = 0;
    real D[27][B], H[30][B];
    for (int64_t base = e0; base < e1; base += B) {
        int n = (e1 - base) < B ? (int)(e1 - base) : B;
        const real *Mp = Bm + 9 * base, *Vp = vol + base;
        real *Qp = q + 16 * base;
        const int32_t *restrict T = el + 10 * base;   /* node a of lane i: T[a B + i]; padding: vertex 0 */
        double P0[3][B];
        for (int c = 0; c < 3; c++) {
            #pragma omp simd
            for (int i = 0; i < B; i++) P0[c][i] = x[3 * T[i] + c];
        }
        for (int a = 1; a < 10; a++)
            for (int c = 0; c < 3; c++) {
                #pragma omp simd
                for (int i = 0; i < B; i++) D[3 * (a - 1) + c][i] = x[3 * T[a * B + i] + c] - P0[c][i];
            }
        memset(H, 0, sizeof(H));
        inverted += NAME(p2_point)(QA, QB, QB, QB, D, Mp, Vp, Qp, mu, lam, H)
                  | NAME(p2_point)(QB, QA, QB, QB, D, Mp, Vp, Qp + 4 * B, mu, lam, H)
                  | NAME(p2_point)(QB, QB, QA, QB, D, Mp, Vp, Qp + 8 * B, mu, lam, H)
                  | NAME(p2_point)(QB, QB, QB, QA, D, Mp, Vp, Qp + 12 * B, mu, lam, H);
        for (int i = 0; i < n; i++)
            for (int a = 0; a < 10; a++) {
                const int64_t v = 3 * (int64_t)T[a * B + i];
                for (int c = 0; c < 3; c++) f[v + c] += H[3 * a + c][i];
            }
    }
    return inverted;
}

/* 6-node triangles [e0, e1) into f (nv, 2), plane strain (reference.p2_forces_range_2d): corners 0-2,
 * edges 3 (0,1) 4 (1,2) 5 (0,2); the exact 2D polar rotation at each of 3 quadrature points. */
static int NAME(p2_forces_range_2d)(const double *restrict x, const int32_t *restrict el, const real *restrict Bm,
        const real *restrict vol, real mu, real lam, double *restrict f, int64_t e0, int64_t e1)
{
    static const real QL[3][3] = {{R_(2.0) / 3, R_(1.0) / 6, R_(1.0) / 6}, {R_(1.0) / 6, R_(2.0) / 3, R_(1.0) / 6}, {R_(1.0) / 6, R_(1.0) / 6, R_(2.0) / 3}};
    static const int EI[3] = {0, 1, 0}, EJ[3] = {1, 2, 2};
    int inverted = 0;
    for (int64_t e = e0; e < e1; e++) {
        const int32_t *t = el + 6 * e;
        const real *bm = Bm + 4 * e;
        real b00 = bm[0], b01 = bm[1], b10 = bm[2], b11 = bm[3], V = -vol[e] / R_(3.0);
        real d[6][2], h[6][2] = {{R_(0.0)}};
        for (int a = 0; a < 6; a++) for (int c = 0; c < 2; c++) d[a][c] = x[2 * t[a] + c] - x[2 * t[0] + c];
        int bad = 0;
        for (int k = 0; k < 3; k++) {
            const real L[3] = {QL[k][0], QL[k][1], QL[k][2]};
            real e1v[2], e2v[2];
            for (int c = 0; c < 2; c++) {
                real y0 = R_(4.0) * (L[1] * d[3][c] + L[2] * d[5][c]);
                e1v[c] = (R_(4.0) * L[1] - R_(1.0)) * d[1][c] + R_(4.0) * (L[0] * d[3][c] + L[2] * d[4][c]) - y0;
                e2v[c] = (R_(4.0) * L[2] - R_(1.0)) * d[2][c] + R_(4.0) * (L[0] * d[5][c] + L[1] * d[4][c]) - y0;
            }
            real f00 = e1v[0] * b00 + e2v[0] * b10, f01 = e1v[0] * b01 + e2v[0] * b11;
            real f10 = e1v[1] * b00 + e2v[1] * b10, f11 = e1v[1] * b01 + e2v[1] * b11;
            bad |= f00 * f11 - f01 * f10 <= R_(0.0);
            real cs = f00 + f11, sn = f10 - f01;
            real inv_n = R_(1.0) / RSQRT(cs * cs + sn * sn + R_(1e-30));
            cs *= inv_n; sn *= inv_n;
            real s00 = cs * f00 + sn * f10, s11 = -sn * f01 + cs * f11;
            real s01 = R_(0.5) * ((cs * f01 + sn * f11) + (-sn * f00 + cs * f10));
            real e00 = s00 - R_(1.0), e11 = s11 - R_(1.0), tr = lam * (e00 + e11);
            real t00 = R_(2.0) * mu * e00 + tr, t11 = R_(2.0) * mu * e11 + tr, t01 = R_(2.0) * mu * s01;
            real p00 = V * (cs * t00 - sn * t01), p01 = V * (cs * t01 - sn * t11);
            real p10 = V * (sn * t00 + cs * t01), p11 = V * (sn * t01 + cs * t11);
            real g[3][2];
            g[1][0] = p00 * b00 + p01 * b01; g[1][1] = p10 * b00 + p11 * b01;
            g[2][0] = p00 * b10 + p01 * b11; g[2][1] = p10 * b10 + p11 * b11;
            g[0][0] = -(g[1][0] + g[2][0]); g[0][1] = -(g[1][1] + g[2][1]);
            for (int j = 0; j < 3; j++) for (int c = 0; c < 2; c++) h[j][c] += (R_(4.0) * L[j] - R_(1.0)) * g[j][c];
            for (int m = 0; m < 3; m++)
                for (int c = 0; c < 2; c++) h[3 + m][c] += R_(4.0) * (L[EI[m]] * g[EJ[m]][c] + L[EJ[m]] * g[EI[m]][c]);
        }
        inverted += bad;
        for (int a = 0; a < 6; a++) for (int c = 0; c < 2; c++) f[2 * t[a] + c] += h[a][c];
    }
    return inverted;
}

/* Triangle forces of elements [e0, e1) into f (nv, 2), plane strain (reference.forces_range_2d). */
static int NAME(forces_range_2d)(const double *restrict x, const int32_t *restrict el, const real *restrict Bm,
        const real *restrict vol, real mu, real lam, double *restrict f, int64_t e0, int64_t e1)
{
    int inverted = 0;
    for (int64_t e = e0; e < e1; e++) {
        const int32_t *t = el + 3 * e;
        const real *b = Bm + 4 * e;
        real d1x = x[2 * t[1]] - x[2 * t[0]], d1y = x[2 * t[1] + 1] - x[2 * t[0] + 1];
        real d2x = x[2 * t[2]] - x[2 * t[0]], d2y = x[2 * t[2] + 1] - x[2 * t[0] + 1];
        real b00 = b[0], b01 = b[1], b10 = b[2], b11 = b[3];
        real f00 = d1x * b00 + d2x * b10, f01 = d1x * b01 + d2x * b11;
        real f10 = d1y * b00 + d2y * b10, f11 = d1y * b01 + d2y * b11;
        inverted += f00 * f11 - f01 * f10 <= R_(0.0);
        real c = f00 + f11, s = f10 - f01;   /* the exact polar rotation of a 2x2 F */
        real inv_n = R_(1.0) / RSQRT(c * c + s * s + R_(1e-30));
        c *= inv_n; s *= inv_n;
        real s00 = c * f00 + s * f10, s11 = -s * f01 + c * f11;
        real s01 = R_(0.5) * ((c * f01 + s * f11) + (-s * f00 + c * f10));
        real e00 = s00 - R_(1.0), e11 = s11 - R_(1.0), tr = lam * (e00 + e11);
        real t00 = R_(2.0) * mu * e00 + tr, t11 = R_(2.0) * mu * e11 + tr, t01 = R_(2.0) * mu * s01, V = -vol[e];
        real p00 = V * (c * t00 - s * t01), p01 = V * (c * t01 - s * t11);
        real p10 = V * (s * t00 + c * t01), p11 = V * (s * t01 + c * t11);
        real h00 = p00 * b00 + p01 * b01, h10 = p10 * b00 + p11 * b01;
        real h01 = p00 * b10 + p01 * b11, h11 = p10 * b10 + p11 * b11;
        f[2 * t[1]] += h00; f[2 * t[1] + 1] += h10;
        f[2 * t[2]] += h01; f[2 * t[2] + 1] += h11;
        f[2 * t[0]] -= h00 + h01; f[2 * t[0] + 1] -= h10 + h11;
    }
    return inverted;
}

/* The elastic forces of elements [e0, e1) of the step's body into f, by element kind. */
static int NAME(element_forces)(const Step *s, double *f, int64_t e0, int64_t e1)
{
    const real *Bm = s->Bm, *vol = s->vol;
    real *q = s->q;
    return s->nodes == 10 ? NAME(p2_forces_blocked)(s->x, s->el, Bm, vol, s->mu, s->lam, q, f, e0, e1)
         : s->nodes == 6 ? NAME(p2_forces_range_2d)(s->x, s->el, Bm, vol, s->mu, s->lam, f, e0, e1)
         : s->dim == 3 ? NAME(forces_blocked)(s->x, s->el, Bm, vol, s->mu, s->lam, q, f, e0, e1)
                       : NAME(forces_range_2d)(s->x, s->el, Bm, vol, s->mu, s->lam, f, e0, e1);
}
