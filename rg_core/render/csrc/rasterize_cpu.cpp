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
#include <cstring>
#include <numeric>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif
#if defined(__SSE2__) || defined(__AVX__)
#include <immintrin.h>
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

// The box of pixels where a Gaussian can reach alpha >= 1/255, from its conic: the ellipse
// a dx^2 + 2 b dx dy + c dy^2 <= -2 thr, widened by kSpanMargin pixels on each side. Pixels outside
// are ones the per-pixel test skips anyway (inside, the power test decides), so visiting only the box
// changes nothing but the time. The margin covers float32 rounding of the per-pixel power, which is
// far below it: eps2d keeps a, c <= 1 / eps2d, so the power's slope across the boundary is bounded
// and its rounding moves the boundary by ~1e-5 px.
constexpr double kSpanMargin = 0.05;

struct Footprint {
  double u, v, q, det, dx_max, dy_max;
  bool degenerate;
  Footprint(const TileData& td, int64_t j) {
    const double a = td.a[j], b = td.b[j], c = td.c[j];
    u = td.u[j]; v = td.v[j];
    q = -2.0 * double(td.thr[j]);
    det = a * c - b * b;
    degenerate = !(det > 0.0) || !(a > 0.0) || !(q > 0.0);  // then visit the whole tile
    dx_max = degenerate ? 0.0 : std::sqrt(q * c / det);
    dy_max = degenerate ? 0.0 : std::sqrt(q * a / det);
  }
  void rows(int y0, int y1, int& r0, int& r1) const {  // [r0, r1) within [y0, y1)
    if (degenerate) { r0 = y0; r1 = y1; return; }
    r0 = std::max(y0, int(std::max(std::ceil(v - dy_max - kSpanMargin), -1.0)));
    r1 = std::min(y1, int(std::min(std::floor(v + dy_max + kSpanMargin) + 1.0, 1e9)));
  }
  bool cols(int x0, int x1, int& c0, int& c1) const {  // [c0, c1) within [x0, x1); false if empty
    if (degenerate) { c0 = x0; c1 = x1; return true; }
    c0 = std::max(x0, int(std::max(std::ceil(u - dx_max - kSpanMargin), -1.0)));
    c1 = std::min(x1, int(std::min(std::floor(u + dx_max + kSpanMargin) + 1.0, 1e9)));
    return c0 < c1;
  }
};

// ---- Lane vectors (GCC/Clang vector extensions): 8 floats in an AVX register where the build enables
// AVX, else 4 (SSE, NEON). A footprint is visited in whole blocks of kLanes pixels of a row, the lanes
// outside it masked: rows of a footprint are ~8 px long, and a per-pixel loop spent most of its time
// in branches and scalar exp calls.
#ifdef __AVX__
constexpr int kLanes = 8;
#else
constexpr int kLanes = 4;
#endif
typedef float vf __attribute__((vector_size(4 * kLanes)));
typedef int32_t vi __attribute__((vector_size(4 * kLanes)));

inline vf ld(const float* p) { vf v; std::memcpy(&v, p, sizeof v); return v; }
inline vi ldi(const int32_t* p) { vi v; std::memcpy(&v, p, sizeof v); return v; }
inline void st(float* p, vf v) { std::memcpy(p, &v, sizeof v); }
inline void sti(int32_t* p, vi v) { std::memcpy(p, &v, sizeof v); }
inline vf splat(float x) { return vf{} + x; }
inline vf sel(vi m, vf a, vf b) { return m ? a : b; }
inline vi seli(vi m, vi a, vi b) { return m ? a : b; }
inline int mask_bits(vi m) {  // bit l set where lane l is true
#if defined(__AVX__)
  return _mm256_movemask_ps(reinterpret_cast<__m256>(m));
#elif defined(__SSE2__)
  return _mm_movemask_ps(reinterpret_cast<__m128>(m));
#else
  int bits = 0;
  for (int l = 0; l < kLanes; ++l) bits |= (m[l] != 0) << l;
  return bits;
#endif
}
inline bool any(vi m) { return mask_bits(m) != 0; }
inline int count(vi m) { return __builtin_popcount(unsigned(mask_bits(m))); }
inline float hsum(vf v) {
  float s = 0.0f;
  for (int l = 0; l < kLanes; ++l) s += v[l];
  return s;
}
inline vi lane_index() {
  vi v;
  for (int l = 0; l < kLanes; ++l) v[l] = l;
  return v;
}

// exp(x) for the rasterizer's powers, x <= 0 (below -87: ~0; NaN lanes give a finite value and are
// masked by the callers), correctly rounded to float but for ~1e-6 of inputs, as glibc's expf: the
// reduction x = k ln2 + r (|r| <= ln2 / 2) and a degree-10 Taylor polynomial of exp(r) run in double
// (truncation error < 3e-13). Matching the reference's exp to the last bit matters: a 1-ulp
// difference can move a pixel across the alpha >= 1/255 or T >= 1e-4 test and with it a gradient.
typedef double vd __attribute__((vector_size(8 * kLanes)));
typedef int64_t vl __attribute__((vector_size(8 * kLanes)));
inline vf exp_nonpos(vf xf) {
  xf = sel(xf > -87.0f, xf, splat(-87.0f));
  xf = sel(xf < 0.0f, xf, splat(0.0f));
  const vd x = __builtin_convertvector(xf, vd);
  // k = round(x / ln2) by the 1.5 * 2^52 shifter: k + shifter is exact, and its bits minus the
  // shifter's are k (no double -> int64 conversion, which AVX2 lacks)
  const vd shifter = vd{} + 6755399441055744.0;
  const vd ks = x * 1.4426950408889634 + shifter;
  const vd kd = ks - shifter;
  const vl k = reinterpret_cast<vl>(ks) - reinterpret_cast<vl>(shifter);
  const vd r = (x - kd * 0.693147180369123816490) - kd * 1.90821492927058770002e-10;
  vd p = vd{} + 1.0 / 3628800.0;
  p = p * r + 1.0 / 362880.0;
  p = p * r + 1.0 / 40320.0;
  p = p * r + 1.0 / 5040.0;
  p = p * r + 1.0 / 720.0;
  p = p * r + 1.0 / 120.0;
  p = p * r + 1.0 / 24.0;
  p = p * r + 1.0 / 6.0;
  p = p * r + 0.5;
  p = p * r + 1.0;
  p = p * r + 1.0;
  const vd y = p * reinterpret_cast<vd>((k + 1023) << 52);  // times 2^k (k >= -126: a normal double)
  return __builtin_convertvector(y, vf);
}

const vi kLaneIdx = lane_index();

// The tile-local colour (and its gradient) is channel-major: a block updates kLanes pixels of a channel
// per instruction. (Pixel-major, one live pixel's channels per instruction, was slower even at 36.)
void forward_tiles(const float* m2, const float* cn, const float* op, const float* col, int64_t C, int W, int H,
                   int TS, const int64_t* offsets, const int32_t* gids, float* out_p, float* tf_p, int32_t* nc_p,
                   int32_t* id_p, int nthreads) {
  const int tiles_x = (W + TS - 1) / TS, tiles_y = (H + TS - 1) / TS;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  const int RS = (TS + kLanes - 1) / kLanes * kLanes;  // row stride of the tile-local arrays
#pragma omp parallel num_threads(nthreads)
  {
    TileData td;
    // Tile-local state, one slot per pixel in rows of RS (whole blocks of kLanes).
    std::vector<float> T, best_w, acc;
    std::vector<int32_t> best, last, done, row_done;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = offsets[t], k = offsets[t + 1] - s;
      const int32_t* ids = gids + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      const int y0 = ty * TS, y1 = std::min(y0 + TS, H), x0 = tx * TS, x1 = std::min(x0 + TS, W);
      const int tw = x1 - x0, P = RS * (y1 - y0), n_pix = tw * (y1 - y0);
      T.assign(P, 1.0f); best_w.assign(P, 0.0f); best.assign(P, -1); last.assign(P, 0); done.assign(P, 0);
      row_done.assign(y1 - y0, 0);  // per tile row: pixels already done (saturated rows are skipped)
      acc.assign(int64_t(P) * C, 0.0f);  // [C, P]
      float* const acc_p = acc.data();
      int n_done = 0;
      // Gaussian-major: each Gaussian visits only its footprint's box, in 8-pixel blocks; every pixel
      // still sees the Gaussians in depth order with the same tests as the per-pixel definition (the
      // box holds every pixel that passes them: the others fail the power test).
      for (int64_t j = 0; j < k && n_done < n_pix; ++j) {
        const Footprint fp(td, j);
        int r0, r1, c0, c1;
        fp.rows(y0, y1, r0, r1);
        if (!fp.cols(x0, x1, c0, c1)) continue;
        const float* __restrict cg = col + int64_t(ids[j]) * C;
        const float uj = td.u[j], vj = td.v[j], aj = td.a[j], bj = td.b[j], cj = td.c[j], oj = td.o[j];
        const float thrj = td.thr[j];
        const int32_t gid_j = ids[j], next = int32_t(j + 1);
        for (int py = r0; py < r1; ++py) {
          if (row_done[py - y0] == tw) continue;
          const float dy = vj - float(py);
          const float cdy = cj * dy * dy;  // power below: the reference's order of operations (rounding)
          for (int bx = (c0 - x0) / kLanes * kLanes; bx < c1 - x0; bx += kLanes) {
            const int p0 = (py - y0) * RS + bx;
            const vi px = kLaneIdx + (x0 + bx);
            const vf dx = uj - __builtin_convertvector(px, vf);
            const vf power = -0.5f * (aj * dx * dx + cdy) - bj * dx * dy;
            const vf raw = oj * exp_nonpos(power);
            const vf alpha = sel(raw < kAlphaMax, raw, splat(kAlphaMax));
            const vi dn = ldi(&done[p0]);
            const vi live = (px >= c0) & (px < c1) & (dn == 0) & (power <= 0.0f) & (power >= thrj) &
                             (alpha >= kAlphaMin);
            if (!any(live)) continue;
            const vf Tc = ld(&T[p0]);
            const vf next_T = Tc * (1.0f - alpha);
            const vi sat = live & (next_T < kTMin);
            const vi blend = live & ~sat;
            const vf w = sel(blend, alpha * Tc, splat(0.0f));
            if (any(sat)) {
              sti(&done[p0], dn | (sat & 1));
              const int ns = count(sat);
              n_done += ns;
              row_done[py - y0] += ns;
            }
            const vf bw = ld(&best_w[p0]);
            const vi better = blend & (w > bw);
            st(&best_w[p0], sel(better, w, bw));
            sti(&best[p0], seli(better, vi{} + gid_j, ldi(&best[p0])));
            st(&T[p0], sel(blend, next_T, Tc));
            sti(&last[p0], seli(blend, vi{} + next, ldi(&last[p0])));
            for (int64_t ch = 0; ch < C; ++ch) {
              float* a = acc_p + ch * P + p0;
              st(a, ld(a) + w * cg[ch]);
            }
          }
        }
      }
      for (int py = y0; py < y1; ++py) {
        for (int px = x0; px < x1; ++px) {
          const int p = (py - y0) * RS + (px - x0);
          const int64_t pix = int64_t(py) * W + px;
          float* __restrict o = out_p + pix * C;
          for (int64_t ch = 0; ch < C; ++ch) o[ch] = acc_p[ch * P + p];
          tf_p[pix] = T[p]; nc_p[pix] = last[p]; id_p[pix] = best[p];
        }
      }
    }
  }
}

// Per tile, back to front: the gradient of each list entry into its row of ent [M, 6 + C]; without
// kGeom only the colour gradient (a feature render of fixed Gaussians: no Sg, no shape terms).
template <bool kGeom>
void backward_tiles(const float* m2, const float* cn, const float* op, const float* col, int64_t C, int W, int H,
                    int TS, const int64_t* off, const int32_t* gid, const float* tf, const int32_t* nc,
                    const float* go, const float* ga, float* ent_p, int nthreads) {
  const int tiles_x = (W + TS - 1) / TS, tiles_y = (H + TS - 1) / TS;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  const int RS = (TS + kLanes - 1) / kLanes * kLanes;
  const int64_t stride = 6 + C;
#pragma omp parallel num_threads(nthreads)
  {
    TileData td;
    // Tile-local, rows of RS: transmittance, Sg, dL/dalpha x T_final, list prefix, dL/dcolour [C, P];
    // the colour gradient of one Gaussian, per channel and lane.
    std::vector<float> T, Sg, gatf, gout_t;
    std::vector<int32_t> ncp;
    std::vector<int> row_nc;
    std::vector<vf> lane_c;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = off[t], k = off[t + 1] - s;
      if (k == 0) continue;
      const int32_t* ids = gid + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      const int y0 = ty * TS, y1 = std::min(y0 + TS, H), x0 = tx * TS, x1 = std::min(x0 + TS, W);
      const int P = RS * (y1 - y0);
      T.assign(P, 1.0f); gatf.assign(P, 0.0f); ncp.assign(P, 0); gout_t.assign(int64_t(P) * C, 0.0f);
      Sg.assign(P, 0.0f);  // per pixel: dL/dcolour . (sum over Gaussians behind of c_j alpha_j T_j)
      lane_c.resize(C);
      int max_nc = 0;
      row_nc.assign(y1 - y0, 0);  // per tile row: the longest list prefix any pixel used
      for (int py = y0; py < y1; ++py)
        for (int px = x0; px < x1; ++px) {
          const int64_t pix = int64_t(py) * W + px;
          const int p = (py - y0) * RS + (px - x0);
          T[p] = tf[pix];
          gatf[p] = ga[pix] * tf[pix];
          ncp[p] = nc[pix];
          for (int64_t ch = 0; ch < C; ++ch) gout_t[ch * P + p] = go[pix * C + ch];
          row_nc[py - y0] = std::max(row_nc[py - y0], int(nc[pix]));
        }
      for (int r : row_nc) max_nc = std::max(max_nc, r);
      const float* const gt = gout_t.data();
      std::fill(ent_p + (s + max_nc) * stride, ent_p + (s + k) * stride, 0.0f);  // never reached
      // Back to front, Gaussian-major over footprints; per pixel the same sequence as the forward.
      for (int64_t j = int64_t(max_nc) - 1; j >= 0; --j) {
        const Footprint fp(td, j);
        int r0, r1, c0, c1;
        fp.rows(y0, y1, r0, r1);
        float* __restrict row = ent_p + (s + j) * stride;
        std::fill_n(row, stride, 0.0f);
        if (!fp.cols(x0, x1, c0, c1)) continue;
        const int32_t gi = ids[j];
        const float* __restrict cg = col + int64_t(gi) * C;
        const float uj = td.u[j], vj = td.v[j], aj = td.a[j], bj = td.b[j], cj = td.c[j], oj = td.o[j];
        const float thrj = td.thr[j];
        const int32_t jj = int32_t(j);
        const vf zero = splat(0.0f);
        vf l_u = zero, l_v = zero, l_a = zero, l_b = zero, l_c = zero, l_o = zero;
        bool touched = false;
        for (int py = r0; py < r1; ++py) {
          if (j >= row_nc[py - y0]) continue;
          const float dy = vj - float(py);
          const float cdy = cj * dy * dy, bdy = bj * dy;  // power: the reference's order of operations
          for (int bx = (c0 - x0) / kLanes * kLanes; bx < c1 - x0; bx += kLanes) {
            const int p0 = (py - y0) * RS + bx;
            const vi px = kLaneIdx + (x0 + bx);
            const vf dx = uj - __builtin_convertvector(px, vf);
            const vf power = -0.5f * (aj * dx * dx + cdy) - bj * dx * dy;
            const vf vis = exp_nonpos(power);
            const vf raw = oj * vis;
            const vf alpha = sel(raw < kAlphaMax, raw, splat(kAlphaMax));
            const vi live = (px >= c0) & (px < c1) & (ldi(&ncp[p0]) > jj) & (power <= 0.0f) &
                             (power >= thrj) & (alpha >= kAlphaMin);
            if (!any(live)) continue;
            if (!touched) {
              std::fill(lane_c.begin(), lane_c.end(), zero);
              touched = true;
            }
            const vf inv = 1.0f / (1.0f - alpha);
            const vf Tp = ld(&T[p0]);
            const vf Tj = Tp * inv;  // transmittance in front of Gaussian j
            st(&T[p0], sel(live, Tj, Tp));
            const vf w = sel(live, alpha * Tj, zero);
            if constexpr (!kGeom) {  // dL/dc_j = sum of w dL/dcolour, nothing else
              for (int64_t ch = 0; ch < C; ++ch) lane_c[ch] += w * sel(live, ld(gt + ch * P + p0), zero);
              continue;
            }
            // gc = dL/dcolour . c_j per pixel, and dL/dc_j = sum of w dL/dcolour
            vf gc = zero;
            for (int64_t ch = 0; ch < C; ++ch) {
              const vf g = sel(live, ld(gt + ch * P + p0), zero);
              gc += g * cg[ch];
              lane_c[ch] += w * g;
            }
            // dL/dalpha_j = sum_ch gout (c_j T_j - S / (1 - alpha_j)), S = colour composited behind j;
            // only gout . S enters, kept as one scalar per pixel (Sg).
            const vf sg = ld(&Sg[p0]);
            const vf dot = Tj * gc - sg * inv;
            st(&Sg[p0], sel(live, sg + w * gc, sg));
            const vi shape = live & ~(raw > kAlphaMax);  // clamped alpha: no gradient to opacity or shape
            const vf dL_dalpha = ld(&gatf[p0]) * inv + dot;
            const vf dL_dpower = sel(shape, dL_dalpha * alpha, zero);
            l_o += sel(shape, dL_dalpha * vis, zero);
            l_a += dL_dpower * (-0.5f * dx * dx);
            l_b += dL_dpower * (-dx * dy);
            l_c += dL_dpower * (-0.5f * dy * dy);
            l_u += dL_dpower * (-(aj * dx + bdy));
            l_v += dL_dpower * (-(cj * dy + bj * dx));
          }
        }
        if (touched) {
          row[0] = hsum(l_u); row[1] = hsum(l_v); row[2] = hsum(l_a); row[3] = hsum(l_b); row[4] = hsum(l_c);
          row[5] = hsum(l_o);
          for (int64_t ch = 0; ch < C; ++ch) row[6 + ch] = hsum(lane_c[ch]);
        }
      }
    }
  }
}

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
  forward_tiles(m2, cn, op, col, C, width, height, tile, offsets, gids, out_p, tf_p, nc_p, id_p, nthreads);
}

// Gradients w.r.t. means2d [N, 2], conics [N, 3], opacities [N], colors [N, C] into grads [N, 6 + C]
// (du, dv, da, db, dc, do, dcolor x C), given dL/dcolour [H, W, C] and dL/d(accumulated alpha) [H, W].
// Walks each pixel's list back to front. geometry = 0: the first six columns are left at 0 (no
// gradient wanted for the Gaussians' shape, position or opacity).
void rg_rasterize_backward(const float* m2, const float* cn, const float* op, const float* col, int64_t n,
                           int64_t C, int width, int height, int tile, const int64_t* off, const int32_t* gid,
                           const float* tf, const int32_t* nc, const float* go, const float* ga, float* tp,
                           int geometry, int nthreads) {
  const int tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
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
  (geometry ? backward_tiles<true> : backward_tiles<false>)(m2, cn, op, col, C, width, height, tile, off, gid, tf, nc,
                                                              go, ga, ent_p, nt);
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
