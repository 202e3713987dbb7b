// EWA projection of 3D Gaussians (forward and hand-written backward), the C++ twin of
// rg_core/render/projection.py: same sanitising, clamps and float64 arithmetic per Gaussian,
// outputs in float32. Tests bind the two (values and gradients).
//
// Plain C++ with a C ABI (no torch headers: it builds in seconds); rg_core/render/fast_cpu.py
// allocates every array with torch and passes pointers through ctypes.
#include <cstdint>

#include <algorithm>
#include <cmath>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;

struct Cam {
  double R[9], t[3], fx, fy, cx, cy, near, far, eps2d;
  int W, H;
  double lxp, lxn, lyp, lyn, max_radius;
};

// wp: world-to-camera [4, 4] row-major, kp: intrinsics [3, 3] row-major, both float64.
Cam make_cam(const double* wp, const double* kp, int64_t W, int64_t H, double near, double far, double eps2d) {
  Cam c;
  for (int r = 0; r < 3; ++r) {
    for (int q = 0; q < 3; ++q) c.R[3 * r + q] = wp[4 * r + q];
    c.t[r] = wp[4 * r + 3];
  }
  c.fx = kp[0]; c.fy = kp[4]; c.cx = kp[2]; c.cy = kp[5];
  c.near = near; c.far = far; c.eps2d = eps2d; c.W = int(W); c.H = int(H);
  const double tfx = 0.5 * W / c.fx, tfy = 0.5 * H / c.fy;
  c.lxp = (W - (c.cx + 0.5)) / c.fx + 0.3 * tfx;
  c.lxn = (c.cx + 0.5) / c.fx + 0.3 * tfx;
  c.lyp = (H - (c.cy + 0.5)) / c.fy + 0.3 * tfy;
  c.lyn = (c.cy + 0.5) / c.fy + 0.3 * tfy;
  c.max_radius = 4.0 * std::sqrt(double(W) * W + double(H) * H);
  return c;
}

// Everything the backward pass needs about one Gaussian, recomputed from the inputs.
struct Geo {
  bool valid;
  double s[3], sgn[3];      // |s| clamped, d|s|/ds (0 where clamped)
  double qn[4], qnorm;      // normalised quaternion and the norm (0: identity used)
  double Rq[9];
  double x, y, z, tx, ty;
  bool tx_free, ty_free;    // x/z, y/z inside the field-of-view clamp
  double j0[3], j1[3], t0[3], t1[3];
  double a, b, c, det, o, o_pass;
  double u, v;
  int radius;
};

void quat_rot(const double* q, double* R) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

Geo compute(const Cam& cam, const float* m, const float* s, const float* q, float o_in) {
  Geo g{};
  bool finite = std::isfinite(o_in);
  for (int k = 0; k < 3; ++k) finite = finite && std::isfinite(m[k]) && std::isfinite(s[k]);
  for (int k = 0; k < 4; ++k) finite = finite && std::isfinite(q[k]);
  g.valid = false;
  if (!finite) return g;
  for (int k = 0; k < 3; ++k) {  // |s| clamped to [1e-9, 1e6] m (reasons in projection.py)
    const double sv = s[k], as = std::fabs(sv);
    g.s[k] = std::min(std::max(as, 1e-9), 1e6);
    g.sgn[k] = (as >= 1e-9 && as <= 1e6) ? (sv > 0 ? 1.0 : (sv < 0 ? -1.0 : 0.0)) : 0.0;
  }
  g.o = std::min(std::max(double(o_in), 0.0), 1.0);
  g.o_pass = (o_in >= 0.0f && o_in <= 1.0f) ? 1.0 : 0.0;
  const double qd[4] = {q[0], q[1], q[2], q[3]};
  const double nrm = std::sqrt(qd[0] * qd[0] + qd[1] * qd[1] + qd[2] * qd[2] + qd[3] * qd[3]);
  if (nrm > 1e-30) {
    for (int k = 0; k < 4; ++k) g.qn[k] = qd[k] / nrm;
    g.qnorm = nrm;
  } else {  // no direction: identity, no gradient
    g.qn[0] = 1; g.qn[1] = g.qn[2] = g.qn[3] = 0; g.qnorm = 0;
  }
  quat_rot(g.qn, g.Rq);
  const double* R = cam.R;
  g.x = R[0] * m[0] + R[1] * m[1] + R[2] * m[2] + cam.t[0];
  g.y = R[3] * m[0] + R[4] * m[1] + R[5] * m[2] + cam.t[1];
  g.z = R[6] * m[0] + R[7] * m[1] + R[8] * m[2] + cam.t[2];
  if (!(g.z >= cam.near && g.z <= cam.far)) return g;
  const double z = g.z;
  const double rx = g.x / z, ry = g.y / z;
  g.tx_free = rx >= -cam.lxn && rx <= cam.lxp;
  g.ty_free = ry >= -cam.lyn && ry <= cam.lyp;
  g.tx = z * std::min(std::max(rx, -cam.lxn), cam.lxp);
  g.ty = z * std::min(std::max(ry, -cam.lyn), cam.lyp);
  for (int k = 0; k < 3; ++k) {
    g.j0[k] = (cam.fx / z) * R[k] - (cam.fx * g.tx / (z * z)) * R[6 + k];
    g.j1[k] = (cam.fy / z) * R[3 + k] - (cam.fy * g.ty / (z * z)) * R[6 + k];
  }
  for (int l = 0; l < 3; ++l) {
    g.t0[l] = g.t1[l] = 0;
    for (int k = 0; k < 3; ++k) {
      const double Mkl = g.Rq[3 * k + l] * g.s[l];
      g.t0[l] += g.j0[k] * Mkl;
      g.t1[l] += g.j1[k] * Mkl;
    }
  }
  g.a = g.t0[0] * g.t0[0] + g.t0[1] * g.t0[1] + g.t0[2] * g.t0[2] + cam.eps2d;
  g.b = g.t0[0] * g.t1[0] + g.t0[1] * g.t1[1] + g.t0[2] * g.t1[2];
  g.c = g.t1[0] * g.t1[0] + g.t1[1] * g.t1[1] + g.t1[2] * g.t1[2] + cam.eps2d;
  g.det = g.a * g.c - g.b * g.b;
  if (!(g.det > 1e-12) || g.o < kAlphaMin) return g;
  g.u = cam.fx * g.x / z + cam.cx;
  g.v = cam.fy * g.y / z + cam.cy;
  const double mid = 0.5 * (g.a + g.c);
  const double lam = mid + std::sqrt(std::max(mid * mid - g.det, 0.0));
  const double reach = std::sqrt(2.0 * std::log(g.o / kAlphaMin) * lam);
  const double r = std::ceil(std::min(reach, cam.max_radius));
  const bool on_screen = (g.u + r > -0.5) && (g.u - r < cam.W - 0.5) && (g.v + r > -0.5) && (g.v - r < cam.H - 0.5);
  if (!on_screen || !std::isfinite(g.u) || !std::isfinite(g.v)) return g;
  g.radius = int(r);
  g.valid = true;
  return g;
}

}  // namespace

// -> means2d [N, 2], conics [N, 3], depths [N], opacities [N] (float32), radii [N] int32, written into
// the caller's arrays. Inputs: means [N, 3], scales [N, 3], quats [N, 4], opacities [N], float32.
extern "C" void rg_project_forward(const float* mp, const float* sp, const float* qp, const float* op, int64_t n,
                                   const double* w2c, const double* K, int64_t width, int64_t height, double near,
                                   double far, double eps2d, float* m2, float* cn, float* dp, float* oo,
                                   int32_t* rp, int nthreads) {
  const Cam cam = make_cam(w2c, K, width, height, near, far, eps2d);
#pragma omp parallel for schedule(static, 1024) num_threads(nthreads)
  for (int64_t i = 0; i < n; ++i) {
    const Geo g = compute(cam, mp + 3 * i, sp + 3 * i, qp + 4 * i, op[i]);
    if (!g.valid) {  // dropped: zeros, as in the torch twin
      m2[2 * i] = m2[2 * i + 1] = 0.f;
      cn[3 * i] = cn[3 * i + 1] = cn[3 * i + 2] = 0.f;
      dp[i] = oo[i] = 0.f;
      rp[i] = 0;
      continue;
    }
    m2[2 * i] = float(g.u); m2[2 * i + 1] = float(g.v);
    cn[3 * i] = float(g.c / g.det); cn[3 * i + 1] = float(-g.b / g.det); cn[3 * i + 2] = float(g.a / g.det);
    dp[i] = float(g.z); oo[i] = float(g.o); rp[i] = g.radius;
  }
}

// Gradients of the projection outputs back to means [N, 3], scales [N, 3], quats [N, 4], opacities [N],
// written into gmp, gsp, gqp, gop_out; g_* are dL/d(outputs) of rg_project_forward.
extern "C" void rg_project_backward(const float* mp, const float* sp, const float* qp, const float* op, int64_t n,
                                    const double* w2c, const double* K, int64_t width, int64_t height, double near,
                                    double far, double eps2d, const float* gm2, const float* gcn, const float* gdp,
                                    const float* gop, float* gmp, float* gsp, float* gqp, float* gop_out,
                                    int nthreads) {
  const Cam cam = make_cam(w2c, K, width, height, near, far, eps2d);
  const double* R = cam.R;
#pragma omp parallel for schedule(static, 1024) num_threads(nthreads)
  for (int64_t i = 0; i < n; ++i) {
    const Geo g = compute(cam, mp + 3 * i, sp + 3 * i, qp + 4 * i, op[i]);
    for (int k = 0; k < 3; ++k) gmp[3 * i + k] = gsp[3 * i + k] = 0.f;
    for (int k = 0; k < 4; ++k) gqp[4 * i + k] = 0.f;
    gop_out[i] = 0.f;
    if (!g.valid) continue;
    gop_out[i] = float(gop[i] * g.o_pass);
    const double z = g.z, det = g.det, d2 = det * det, a = g.a, b = g.b, c = g.c;
    // conic = (c, -b, a) / det
    const double gA = gcn[3 * i], gB = gcn[3 * i + 1], gC = gcn[3 * i + 2];
    const double ga = gA * (-c * c / d2) + gB * (b * c / d2) + gC * (-b * b / d2);
    const double gb = gA * (2 * b * c / d2) + gB * (-1.0 / det - 2 * b * b / d2) + gC * (2 * a * b / d2);
    const double gc = gA * (-b * b / d2) + gB * (a * b / d2) + gC * (-a * a / d2);
    double gt0[3], gt1[3];
    for (int l = 0; l < 3; ++l) {
      gt0[l] = 2 * g.t0[l] * ga + g.t1[l] * gb;
      gt1[l] = 2 * g.t1[l] * gc + g.t0[l] * gb;
    }
    double gj0[3] = {0, 0, 0}, gj1[3] = {0, 0, 0}, gRq[9], gsv[3] = {0, 0, 0};
    for (int k = 0; k < 3; ++k) {
      for (int l = 0; l < 3; ++l) {
        const double Mkl = g.Rq[3 * k + l] * g.s[l];
        gj0[k] += gt0[l] * Mkl;
        gj1[k] += gt1[l] * Mkl;
        const double gM = g.j0[k] * gt0[l] + g.j1[k] * gt1[l];
        gRq[3 * k + l] = gM * g.s[l];
        gsv[l] += gM * g.Rq[3 * k + l];
      }
    }
    // j0 = (fx/z) R0 - (fx tx / z^2) R2 ; j1 = (fy/z) R1 - (fy ty / z^2) R2
    const double p0 = gj0[0] * R[0] + gj0[1] * R[1] + gj0[2] * R[2];
    const double q0 = -(gj0[0] * R[6] + gj0[1] * R[7] + gj0[2] * R[8]);
    const double p1 = gj1[0] * R[3] + gj1[1] * R[4] + gj1[2] * R[5];
    const double q1 = -(gj1[0] * R[6] + gj1[1] * R[7] + gj1[2] * R[8]);
    double gz = p0 * (-cam.fx / (z * z)) + q0 * (-2 * cam.fx * g.tx / (z * z * z)) + p1 * (-cam.fy / (z * z)) +
                q1 * (-2 * cam.fy * g.ty / (z * z * z));
    const double gtx = q0 * cam.fx / (z * z), gty = q1 * cam.fy / (z * z);
    double gx = 0, gy = 0;
    if (g.tx_free) gx += gtx; else gz += gtx * (g.tx / z);
    if (g.ty_free) gy += gty; else gz += gty * (g.ty / z);
    const double gu = gm2[2 * i], gv = gm2[2 * i + 1];
    gx += gu * cam.fx / z;
    gy += gv * cam.fy / z;
    gz += -gu * cam.fx * g.x / (z * z) - gv * cam.fy * g.y / (z * z) + gdp[i];
    for (int k = 0; k < 3; ++k) gmp[3 * i + k] = float(R[k] * gx + R[3 + k] * gy + R[6 + k] * gz);
    for (int l = 0; l < 3; ++l) gsp[3 * i + l] = float(gsv[l] * g.sgn[l]);
    if (g.qnorm > 0) {
      const double w = g.qn[0], x = g.qn[1], y = g.qn[2], zz = g.qn[3];
      const double* G = gRq;
      double gq4[4];
      gq4[0] = 2 * (-zz * G[1] + y * G[2] + zz * G[3] - x * G[5] - y * G[6] + x * G[7]);
      gq4[1] = 2 * (y * G[1] + zz * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + zz * G[6] + w * G[7] - 2 * x * G[8]);
      gq4[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + zz * G[5] - w * G[6] + zz * G[7] - 2 * y * G[8]);
      gq4[3] = 2 * (-2 * zz * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * zz * G[4] + y * G[5] + x * G[6] + y * G[7]);
      const double dot = gq4[0] * w + gq4[1] * x + gq4[2] * y + gq4[3] * zz;
      for (int k = 0; k < 4; ++k) gqp[4 * i + k] = float((gq4[k] - g.qn[k] * dot) / g.qnorm);
    }
  }
}
