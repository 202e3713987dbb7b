// Fast CPU Gaussian rasterizer: tile binning, depth sort, front-to-back alpha compositing with
// early termination, and the hand-written backward pass. OpenMP over tiles.
//
// Same function as rg_core/render/reference.py (tests bind the two). Pixel centres are at integer
// coordinates; conics hold (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
//
// Plain C++ with a C ABI (no torch headers: it builds in seconds); rg_core/render/fast_cpu.py
// allocates every array with torch and passes pointers through ctypes. Arrays are C-contiguous.
#include <cstdint>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr float kAlphaMin = 1.0f / 255.0f;  // skip contributions below this (3DGS)
constexpr float kAlphaMax = 0.99f;          // keeps 1 - alpha >= 0.01 for the backward division
constexpr float kTMin = 1e-4f;              // stop once transmittance would fall below this


// Tile rectangle [x0, x1, y0, y1] (inclusive tile indices; x0 > x1 when empty) of each Gaussian
// into rect [N, 4], the list offsets [T + 1] into offsets; returns the total list length M.
int64_t bin_count(const float* means2d, const int32_t* radii, int64_t n, int width, int height, int tile,
                  int32_t* rect, int64_t* offsets) {
  const int tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  std::vector<int64_t> counts(n_tiles + 1, 0);
  for (int64_t i = 0; i < n; ++i) {
    int32_t* r = &rect[4 * i];
    r[0] = 1; r[1] = 0; r[2] = 1; r[3] = 0;  // empty
    if (radii[i] <= 0) continue;
    const float rad = float(radii[i]);
    const float u = means2d[2 * i], v = means2d[2 * i + 1];
    // Same pixel range as the reference: [ceil(u - r), floor(u + r)] clipped to the image.
    auto clampi = [](float x, int hi) { return int(std::min(std::max(x, 0.0f), float(hi))); };
    r[0] = clampi(std::ceil(u - rad), width - 1) / tile;
    r[1] = clampi(std::floor(u + rad), width - 1) / tile;
    r[2] = clampi(std::ceil(v - rad), height - 1) / tile;
    r[3] = clampi(std::floor(v + rad), height - 1) / tile;
    for (int ty = r[2]; ty <= r[3]; ++ty)
      for (int tx = r[0]; tx <= r[1]; ++tx) counts[int64_t(ty) * tiles_x + tx + 1]++;
  }
  std::partial_sum(counts.begin(), counts.end(), offsets);
  return offsets[n_tiles];
}

// Fills gids [M]: per tile the Gaussians touching it, sorted by (depth, id).
void bin_fill(const int32_t* rect, const float* depths, int64_t n, int width, int height, int tile,
              const int64_t* offsets, int32_t* gids, int nthreads) {
  const int tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  std::vector<int64_t> cursor(offsets, offsets + n_tiles);
  for (int64_t i = 0; i < n; ++i) {  // ascending id: lists start in id order (stable)
    const int32_t* r = &rect[4 * i];
    for (int ty = r[2]; ty <= r[3]; ++ty)
      for (int tx = r[0]; tx <= r[1]; ++tx) gids[cursor[int64_t(ty) * tiles_x + tx]++] = int32_t(i);
  }
#pragma omp parallel for schedule(dynamic, 4) num_threads(nthreads)
  for (int64_t t = 0; t < n_tiles; ++t) {
    std::stable_sort(gids + offsets[t], gids + offsets[t + 1],
                     [depths](int32_t a, int32_t c) { return depths[a] < depths[c]; });
  }
}

// Per-Gaussian data of one tile, gathered contiguously (the CPU analogue of shared memory).
struct TileData {
  std::vector<float> u, v, a, b, c, o, thr;
  void load(const int32_t* ids, int64_t k, const float* means2d, const float* conics, const float* opac) {
    u.resize(k); v.resize(k); a.resize(k); b.resize(k); c.resize(k); o.resize(k); thr.resize(k);
    for (int64_t j = 0; j < k; ++j) {
      const int32_t g = ids[j];
      u[j] = means2d[2 * g]; v[j] = means2d[2 * g + 1];
      a[j] = conics[3 * g]; b[j] = conics[3 * g + 1]; c[j] = conics[3 * g + 2];
      o[j] = opac[g];
      // Below this power, alpha = o exp(power) < 1/255 for sure: skip without calling exp. The
      // 1e-4 margin (relative, far above exp's rounding) keeps the exact test for borderline cases,
      // so the result is the same as the reference's.
      thr[j] = std::log(kAlphaMin / std::max(o[j], kAlphaMin)) - 1e-4f;
    }
  }
};

// Pixels of one tile row where a Gaussian can reach alpha >= 1/255, from its conic: the row's
// solutions of a dx^2 + 2 b dx dy + c dy^2 <= -2 thr, widened by kSpanMargin pixels on each side.
// Pixels outside are exactly those the per-pixel test would skip, so visiting only these spans
// changes nothing but the time. The margin covers float32 rounding of the per-pixel power, which is
// far below it: eps2d keeps a, c <= 1 / eps2d, so the power's slope across the boundary is bounded
// and its rounding moves the boundary by ~1e-5 px. (A margin of one pixel visited 2-3x the pixels of
// a small Gaussian's footprint for nothing.) Returns false if the row has none.
constexpr double kSpanMargin = 0.05;

struct Footprint {
  double u, v, a, b, c, q, det, dy_max, inv_a;
  bool degenerate;
  Footprint(const TileData& td, int64_t j) {
    u = td.u[j]; v = td.v[j]; a = td.a[j]; b = td.b[j]; c = td.c[j];
    q = -2.0 * double(td.thr[j]);
    det = a * c - b * b;
    degenerate = !(det > 0.0) || !(a > 0.0) || !(q > 0.0);  // then visit the whole tile
    dy_max = degenerate ? 0.0 : std::sqrt(q * a / det);
    inv_a = degenerate ? 0.0 : 1.0 / a;
  }
  void rows(int y0, int y1, int& r0, int& r1) const {  // [r0, r1) within [y0, y1)
    if (degenerate) { r0 = y0; r1 = y1; return; }
    r0 = std::max(y0, int(std::max(std::ceil(v - dy_max - kSpanMargin), -1.0)));
    r1 = std::min(y1, int(std::min(std::floor(v + dy_max + kSpanMargin) + 1.0, 1e9)));
  }
  bool cols(int py, int x0, int x1, int& c0, int& c1) const {  // [c0, c1) within [x0, x1)
    if (degenerate) { c0 = x0; c1 = x1; return true; }
    const double dy = v - py;
    const double disc = q * a - det * dy * dy;
    if (disc < 0.0) return false;
    const double sq = std::sqrt(disc);
    const double lo = u - (-b * dy + sq) * inv_a, hi = u - (-b * dy - sq) * inv_a;
    c0 = std::max(x0, int(std::max(std::ceil(lo - kSpanMargin), -1.0)));
    c1 = std::min(x1, int(std::min(std::floor(hi + kSpanMargin) + 1.0, 1e9)));
    return c0 < c1;
  }
};

}  // namespace

extern "C" {

int64_t rg_bin_count(const float* means2d, const int32_t* radii, int64_t n, int width, int height, int tile,
                     int32_t* rect, int64_t* offsets) {
  return bin_count(means2d, radii, n, width, height, tile, rect, offsets);
}

void rg_bin_fill(const int32_t* rect, const float* depths, int64_t n, int width, int height, int tile,
                 const int64_t* offsets, int32_t* gids, int nthreads) {
  bin_fill(rect, depths, n, width, height, tile, offsets, gids, nthreads);
}

// Inputs: means2d [N, 2], conics [N, 3], opacities [N], colors [N, C] (float32), the bins above.
// Writes colour [H, W, C], final transmittance [H, W], count of list entries processed [H, W], id of
// the largest blending weight [H, W] (-1: none). Every element is written, empty tiles included
// (tests fill the outputs with NaN first).
void rg_rasterize_forward(const float* m2, const float* cn, const float* op, const float* col, int64_t n,
                          int64_t C, int width, int height, int tile, const int64_t* offsets,
                          const int32_t* gids, float* out_p, float* tf_p, int32_t* nc_p, int32_t* id_p,
                          int nthreads) {
  (void)n;
  const int W = width, H = height, TS = tile;
  const int tiles_x = (W + TS - 1) / TS, tiles_y = (H + TS - 1) / TS;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
#pragma omp parallel num_threads(nthreads)
  {
    TileData td;
    std::vector<float> T, best_w, acc;
    std::vector<int32_t> best, last, row_done;
    std::vector<uint8_t> done;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = offsets[t], k = offsets[t + 1] - s;
      const int32_t* ids = gids + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      const int y0 = ty * TS, y1 = std::min(y0 + TS, H), x0 = tx * TS, x1 = std::min(x0 + TS, W);
      const int tw = x1 - x0, P = tw * (y1 - y0);
      T.assign(P, 1.0f); best_w.assign(P, 0.0f); best.assign(P, -1); last.assign(P, 0); done.assign(P, 0);
      row_done.assign(y1 - y0, 0);  // per tile row: pixels already done (saturated rows are skipped)
      // colour accumulates in a tile-local buffer (L1-sized at 16 x 16 x 36), copied out at the end
      acc.assign(int64_t(P) * C, 0.0f);
      float* __restrict acc_p = acc.data();
      float* __restrict Tp = T.data();
      int n_done = 0;
      // Gaussian-major: each Gaussian visits only its footprint; every pixel still sees the
      // Gaussians in depth order with the same tests as the per-pixel definition.
      for (int64_t j = 0; j < k && n_done < P; ++j) {
        const Footprint fp(td, j);
        int r0, r1;
        fp.rows(y0, y1, r0, r1);
        const float* __restrict cg = col + int64_t(ids[j]) * C;
        const float uj = td.u[j], vj = td.v[j], aj = td.a[j], bj = td.b[j], cj = td.c[j], oj = td.o[j];
        const float thrj = td.thr[j];
        const int32_t gid_j = ids[j];
        for (int py = r0; py < r1; ++py) {
          int c0, c1;
          if (row_done[py - y0] == tw || !fp.cols(py, x0, x1, c0, c1)) continue;
          const float dy = vj - float(py);
          const int prow = (py - y0) * tw - x0;
          for (int px = c0; px < c1; ++px) {
            const int p = prow + px;
            if (done[p]) continue;
            const float dx = uj - float(px);
            const float power = -0.5f * (aj * dx * dx + cj * dy * dy) - bj * dx * dy;
            if (power > 0.0f || power < thrj) continue;
            const float alpha = std::min(kAlphaMax, oj * std::exp(power));
            if (alpha < kAlphaMin) continue;
            const float Tc = Tp[p];
            const float next_T = Tc * (1.0f - alpha);
            if (next_T < kTMin) { done[p] = 1; ++n_done; ++row_done[py - y0]; continue; }
            const float w = alpha * Tc;
            float* __restrict o_pix = acc_p + int64_t(p) * C;
            for (int64_t ch = 0; ch < C; ++ch) o_pix[ch] += w * cg[ch];
            if (w > best_w[p]) { best_w[p] = w; best[p] = gid_j; }
            Tp[p] = next_T;
            last[p] = int32_t(j + 1);
          }
        }
      }
      for (int py = y0; py < y1; ++py) {
        std::copy_n(acc_p + int64_t((py - y0) * tw) * C, int64_t(tw) * C, out_p + (int64_t(py) * W + x0) * C);
        for (int px = x0; px < x1; ++px) {
          const int p = (py - y0) * tw + (px - x0);
          const int64_t pix = int64_t(py) * W + px;
          tf_p[pix] = T[p]; nc_p[pix] = last[p]; id_p[pix] = best[p];
        }
      }
    }
  }
}

// Gradients w.r.t. means2d [N, 2], conics [N, 3], opacities [N], colors [N, C] into grads [N, 6 + C]
// (du, dv, da, db, dc, do, dcolor x C), given dL/dcolour [H, W, C] and dL/d(accumulated alpha) [H, W].
// Walks each pixel's list back to front.
void rg_rasterize_backward(const float* m2, const float* cn, const float* op, const float* col, int64_t n,
                           int64_t C, int width, int height, int tile, const int64_t* off, const int32_t* gid,
                           const float* tf, const int32_t* nc, const float* go, const float* ga, float* tp,
                           int nthreads) {
  const int W = width, H = height, TS = tile;
  const int tiles_x = (W + TS - 1) / TS, tiles_y = (H + TS - 1) / TS;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  // Each tile writes the gradient of each of its list entries into its own row of `ent` [M, stride]
  // (sequential writes, no atomics), then each Gaussian sums its entries in list order: the result
  // does not depend on the thread count or the schedule. Per-thread [N, stride] buffers cost twice
  // the time here: zeroing them and the scattered read-modify-writes missed the cache.
  const int nt = std::max(nthreads, 1);
  const int64_t stride = 6 + C;
  const int64_t M = off[n_tiles];
  static thread_local std::vector<float> ent;  // reused between calls (no page faults per call)
  static thread_local std::vector<int64_t> g_off, g_ent;
  if (int64_t(ent.size()) < M * stride) ent.resize(M * stride);
  float* const ent_p = ent.data();

#pragma omp parallel num_threads(nt)
  {
    TileData td;
    std::vector<float> T, Sg, acc(stride);
    std::vector<int> row_nc;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = off[t], k = off[t + 1] - s;
      if (k == 0) continue;
      const int32_t* ids = gid + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      const int y0 = ty * TS, y1 = std::min(y0 + TS, H), x0 = tx * TS, x1 = std::min(x0 + TS, W);
      const int tw = x1 - x0, P = tw * (y1 - y0);
      T.resize(P);
      Sg.assign(P, 0.0f);  // per pixel: dL/dcolour . (sum over Gaussians behind of c_j alpha_j T_j)
      int max_nc = 0;
      row_nc.assign(y1 - y0, 0);  // per tile row: the longest list prefix any pixel used
      for (int py = y0; py < y1; ++py)
        for (int px = x0; px < x1; ++px) {
          const int64_t pix = int64_t(py) * W + px;
          T[(py - y0) * tw + (px - x0)] = tf[pix];
          row_nc[py - y0] = std::max(row_nc[py - y0], int(nc[pix]));
        }
      for (int r : row_nc) max_nc = std::max(max_nc, r);
      // Back to front, Gaussian-major over footprints; per pixel the same sequence as the forward.
      float* __restrict Tp = T.data();
      float* __restrict acc_c = acc.data() + 6;
      std::fill(ent_p + (s + max_nc) * stride, ent_p + (s + k) * stride, 0.0f);  // never reached
      for (int64_t j = int64_t(max_nc) - 1; j >= 0; --j) {
        const Footprint fp(td, j);
        int r0, r1;
        fp.rows(y0, y1, r0, r1);
        const int32_t gi = ids[j];
        const float* __restrict cg = col + int64_t(gi) * C;
        const float uj = td.u[j], vj = td.v[j], aj = td.a[j], bj = td.b[j], cj = td.c[j], oj = td.o[j];
        const float thrj = td.thr[j];
        float g_u = 0.f, g_v = 0.f, g_a = 0.f, g_b = 0.f, g_c = 0.f, g_o = 0.f;
        bool touched = false;
        for (int py = r0; py < r1; ++py) {
          int c0, c1;
          if (j >= row_nc[py - y0] || !fp.cols(py, x0, x1, c0, c1)) continue;
          const float dy = vj - float(py);
          for (int px = c0; px < c1; ++px) {
            const int64_t pix = int64_t(py) * W + px;
            if (j >= nc[pix]) continue;
            const int p = (py - y0) * tw + (px - x0);
            const float dx = uj - float(px);
            const float power = -0.5f * (aj * dx * dx + cj * dy * dy) - bj * dx * dy;
            if (power > 0.0f || power < thrj) continue;
            const float vis = std::exp(power);
            const float raw = oj * vis;
            const float alpha = std::min(kAlphaMax, raw);
            if (alpha < kAlphaMin) continue;
            if (!touched) { std::fill(acc.begin(), acc.end(), 0.0f); touched = true; }
            const float inv = 1.0f / (1.0f - alpha);
            const float Tj = Tp[p] * inv;  // transmittance in front of Gaussian j
            Tp[p] = Tj;
            const float w = alpha * Tj;
            const float* __restrict gout = go + pix * C;
            // dL/dalpha_j = sum_ch gout (c_j T_j - S / (1 - alpha_j)), S = colour composited behind j.
            // Only gout . S enters, so it is kept as one scalar per pixel (Sg) instead of S itself:
            // two channel loops per pixel and Gaussian instead of three.
            float gc = 0.f;
#pragma omp simd reduction(+ : gc)
            for (int64_t ch = 0; ch < C; ++ch) gc += gout[ch] * cg[ch];
            for (int64_t ch = 0; ch < C; ++ch) acc_c[ch] += w * gout[ch];
            const float dot = Tj * gc - Sg[p] * inv;
            Sg[p] += w * gc;
            if (raw > kAlphaMax) continue;  // clamped alpha: no gradient to opacity or shape
            const float dL_dalpha = ga[pix] * tf[pix] * inv + dot;
            const float dL_dpower = dL_dalpha * alpha;
            g_o += dL_dalpha * vis;
            g_a += dL_dpower * (-0.5f * dx * dx);
            g_b += dL_dpower * (-dx * dy);
            g_c += dL_dpower * (-0.5f * dy * dy);
            g_u += dL_dpower * (-(aj * dx + bj * dy));
            g_v += dL_dpower * (-(cj * dy + bj * dx));
          }
        }
        float* __restrict row = ent_p + (s + j) * stride;
        if (touched) {
          acc[0] = g_u; acc[1] = g_v; acc[2] = g_a; acc[3] = g_b; acc[4] = g_c; acc[5] = g_o;
          std::copy_n(acc.data(), stride, row);
        } else {
          std::fill_n(row, stride, 0.0f);
        }
      }
    }
  }
  // entries of each Gaussian (CSR by counting), in list order
  g_off.assign(n + 1, 0);
  g_ent.resize(M);
  for (int64_t e = 0; e < M; ++e) g_off[gid[e] + 1]++;
  for (int64_t i = 0; i < n; ++i) g_off[i + 1] += g_off[i];
  {
    std::vector<int64_t> cur(g_off.begin(), g_off.end() - 1);
    for (int64_t e = 0; e < M; ++e) g_ent[cur[gid[e]]++] = e;
  }
  const int64_t* go_p = g_off.data();
  const int64_t* ge_p = g_ent.data();
#pragma omp parallel for schedule(static, 256) num_threads(nt)
  for (int64_t i = 0; i < n; ++i) {
    float* __restrict out = tp + i * stride;
    std::fill_n(out, stride, 0.0f);
    for (int64_t q = go_p[i]; q < go_p[i + 1]; ++q) {
      const float* __restrict row = ent_p + ge_p[q] * stride;
      for (int64_t e = 0; e < stride; ++e) out[e] += row[e];
    }
  }
}

}  // extern "C"
