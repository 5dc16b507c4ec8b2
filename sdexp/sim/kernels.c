/* Co-rotated linear tet forces, the hot loop of sdexp's simulator (see fem.py for the math;
 * fem.corotated_range_3d is the same computation in numba, the reference and fallback).
 *
 * Elements are processed in blocks of B: a scalar gather of F = Ds Dm^-1 into structure-of-
 * arrays buffers, one branch-free loop the compiler turns into SIMD, a scalar scatter. This
 * layout is what lets gcc vectorise it; numba's LLVM keeps the same arithmetic scalar.
 * Threads are OpenMP's: a region costs a microsecond or two, a numba parallel region ten. */
#include <math.h>
#include <stdint.h>
#include <string.h>
#define B 32  /* elements per SIMD block */
#define POLAR_ITERATIONS 2  /* as fem.POLAR_ITERATIONS */
/* Adds the nodal forces of elements [e0, e1) into f (nv, 3) and updates their warm-start
 * quaternions q (ne, 4) by POLAR_ITERATIONS polar iterations. Returns the inverted count. */
static int forces_range(const double *restrict x, const int32_t *restrict el, const double *restrict Bm,
        const double *restrict vol, double mu, double lam, double *restrict q,
        double *restrict f, int64_t e0, int64_t e1)
{
    int inverted = 0;
    double F[9][B], Q[4][B], M[9][B], V[B], H[9][B];
    for (int64_t base = e0; base < e1; base += B) {
        int n = (e1 - base) < B ? (int)(e1 - base) : B;
        for (int i = 0; i < B; i++) {
            if (i >= n) { for (int k = 0; k < 9; k++) { F[k][i] = (k % 4 == 0); M[k][i] = 0; }
                          Q[0][i] = 1; Q[1][i] = Q[2][i] = Q[3][i] = 0; V[i] = 0; continue; }
            int64_t e = base + i;
            const int32_t *t = el + 4 * e;
            const double *p0 = x + 3 * t[0], *p1 = x + 3 * t[1], *p2 = x + 3 * t[2], *p3 = x + 3 * t[3];
            double d[3][3];
            for (int c = 0; c < 3; c++) { d[c][0] = p1[c] - p0[c]; d[c][1] = p2[c] - p0[c]; d[c][2] = p3[c] - p0[c]; }
            const double *b = Bm + 9 * e;
            for (int r = 0; r < 3; r++) for (int c = 0; c < 3; c++)
                F[3 * r + c][i] = d[r][0] * b[c] + d[r][1] * b[3 + c] + d[r][2] * b[6 + c];
            for (int k = 0; k < 9; k++) M[k][i] = b[k];
            for (int k = 0; k < 4; k++) Q[k][i] = q[4 * e + k];
            V[i] = -vol[e];
        }
        #pragma omp simd reduction(+:inverted)
        for (int i = 0; i < B; i++) {
            double f00 = F[0][i], f01 = F[1][i], f02 = F[2][i], f10 = F[3][i], f11 = F[4][i], f12 = F[5][i],
                   f20 = F[6][i], f21 = F[7][i], f22 = F[8][i];
            double det = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20);
            inverted += (det <= 0.0) & (V[i] != 0.0);  /* padding lanes have V = 0 */
            double qw = Q[0][i], qx = Q[1][i], qy = Q[2][i], qz = Q[3][i];
            for (int it = 0; it < POLAR_ITERATIONS; it++) {  /* warm-started polar iteration */
                double r00 = 1.0 - 2.0 * (qy * qy + qz * qz), r01 = 2.0 * (qx * qy - qw * qz), r02 = 2.0 * (qx * qz + qw * qy);
                double r10 = 2.0 * (qx * qy + qw * qz), r11 = 1.0 - 2.0 * (qx * qx + qz * qz), r12 = 2.0 * (qy * qz - qw * qx);
                double r20 = 2.0 * (qx * qz - qw * qy), r21 = 2.0 * (qy * qz + qw * qx), r22 = 1.0 - 2.0 * (qx * qx + qy * qy);
                double wx = (r10 * f20 - r20 * f10) + (r11 * f21 - r21 * f11) + (r12 * f22 - r22 * f12);
                double wy = (r20 * f00 - r00 * f20) + (r21 * f01 - r01 * f21) + (r22 * f02 - r02 * f22);
                double wz = (r00 * f10 - r10 * f00) + (r01 * f11 - r11 * f01) + (r02 * f12 - r12 * f02);
                double den = 0.5 / (fabs(r00 * f00 + r10 * f10 + r20 * f20 + r01 * f01 + r11 * f11 + r21 * f21 + r02 * f02 + r12 * f12 + r22 * f22) + 1e-9);
                double ax = wx * den, ay = wy * den, az = wz * den;
                double nw = qw - ax * qx - ay * qy - az * qz, nx = qx + ax * qw + ay * qz - az * qy;
                double ny = qy - ax * qz + ay * qw + az * qx, nz = qz + ax * qy - ay * qx + az * qw;
                double inv = 1.0 / sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
                qw = nw * inv; qx = nx * inv; qy = ny * inv; qz = nz * inv;
            }
            Q[0][i] = qw; Q[1][i] = qx; Q[2][i] = qy; Q[3][i] = qz;
            double r00 = 1.0 - 2.0 * (qy * qy + qz * qz), r01 = 2.0 * (qx * qy - qw * qz), r02 = 2.0 * (qx * qz + qw * qy);
            double r10 = 2.0 * (qx * qy + qw * qz), r11 = 1.0 - 2.0 * (qx * qx + qz * qz), r12 = 2.0 * (qy * qz - qw * qx);
            double r20 = 2.0 * (qx * qz - qw * qy), r21 = 2.0 * (qy * qz + qw * qx), r22 = 1.0 - 2.0 * (qx * qx + qy * qy);
            double s00 = r00 * f00 + r10 * f10 + r20 * f20, s11 = r01 * f01 + r11 * f11 + r21 * f21, s22 = r02 * f02 + r12 * f12 + r22 * f22;
            double s01 = 0.5 * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20));
            double s02 = 0.5 * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20));
            double s12 = 0.5 * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21));
            double tr = lam * (s00 + s11 + s22 - 3.0), m2 = 2.0 * mu;
            double t00 = m2 * (s00 - 1.0) + tr, t11 = m2 * (s11 - 1.0) + tr, t22 = m2 * (s22 - 1.0) + tr;
            double t01 = m2 * s01, t02 = m2 * s02, t12 = m2 * s12, Vi = V[i];
            double p00 = Vi * (r00 * t00 + r01 * t01 + r02 * t02), p01 = Vi * (r00 * t01 + r01 * t11 + r02 * t12), p02 = Vi * (r00 * t02 + r01 * t12 + r02 * t22);
            double p10 = Vi * (r10 * t00 + r11 * t01 + r12 * t02), p11 = Vi * (r10 * t01 + r11 * t11 + r12 * t12), p12 = Vi * (r10 * t02 + r11 * t12 + r12 * t22);
            double p20 = Vi * (r20 * t00 + r21 * t01 + r22 * t02), p21 = Vi * (r20 * t01 + r21 * t11 + r22 * t12), p22 = Vi * (r20 * t02 + r21 * t12 + r22 * t22);
            double b00 = M[0][i], b01 = M[1][i], b02 = M[2][i], b10 = M[3][i], b11 = M[4][i], b12 = M[5][i], b20 = M[6][i], b21 = M[7][i], b22 = M[8][i];
            H[0][i] = p00 * b00 + p01 * b01 + p02 * b02; H[1][i] = p10 * b00 + p11 * b01 + p12 * b02; H[2][i] = p20 * b00 + p21 * b01 + p22 * b02;
            H[3][i] = p00 * b10 + p01 * b11 + p02 * b12; H[4][i] = p10 * b10 + p11 * b11 + p12 * b12; H[5][i] = p20 * b10 + p21 * b11 + p22 * b12;
            H[6][i] = p00 * b20 + p01 * b21 + p02 * b22; H[7][i] = p10 * b20 + p11 * b21 + p12 * b22; H[8][i] = p20 * b20 + p21 * b21 + p22 * b22;
        }
        for (int i = 0; i < n; i++) {
            int64_t e = base + i;
            for (int k = 0; k < 4; k++) q[4 * e + k] = Q[k][i];
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
