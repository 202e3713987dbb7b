// Fast CPU Gaussian rasterizer: tile binning, depth sort, front-to-back alpha compositing with
// early termination, and the hand-written backward pass. OpenMP over tiles.
//
// Same function as rg_core/render/reference.py (tests bind the two). Pixel centres are at integer
// coordinates; conics hold (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
#include <torch/extension.h>

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

int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

struct Binning {
  std::vector<int64_t> offsets;  // [T + 1]
  std::vector<int32_t> gids;     // [M], per tile sorted by (depth, id)
};

Binning bin_tiles(const float* means2d, const int32_t* radii, const float* depths, int64_t n,
                  int width, int height, int tile) {
  const int tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  std::vector<int32_t> rect(4 * n);
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
  Binning b;
  b.offsets.resize(n_tiles + 1);
  std::partial_sum(counts.begin(), counts.end(), b.offsets.begin());
  b.gids.resize(b.offsets[n_tiles]);
  std::vector<int64_t> cursor(b.offsets.begin(), b.offsets.end() - 1);
  for (int64_t i = 0; i < n; ++i) {  // ascending id: lists start in id order (stable)
    const int32_t* r = &rect[4 * i];
    for (int ty = r[2]; ty <= r[3]; ++ty)
      for (int tx = r[0]; tx <= r[1]; ++tx) b.gids[cursor[int64_t(ty) * tiles_x + tx]++] = int32_t(i);
  }
#pragma omp parallel for schedule(dynamic, 4)
  for (int64_t t = 0; t < n_tiles; ++t) {
    std::stable_sort(b.gids.begin() + b.offsets[t], b.gids.begin() + b.offsets[t + 1],
                     [depths](int32_t a, int32_t c) { return depths[a] < depths[c]; });
  }
  return b;
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

}  // namespace

// -> colour [H, W, C], final transmittance [H, W], count of list entries processed [H, W],
//    id of the largest blending weight [H, W] (-1: none), tile offsets [T + 1], ids [M].
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opacities, torch::Tensor colors,
                                             torch::Tensor radii, torch::Tensor depths, int64_t width,
                                             int64_t height, int64_t tile, bool poison) {
  TORCH_CHECK(means2d.dtype() == torch::kFloat32 && conics.dtype() == torch::kFloat32 &&
                  opacities.dtype() == torch::kFloat32 && colors.dtype() == torch::kFloat32 &&
                  depths.dtype() == torch::kFloat32 && radii.dtype() == torch::kInt32,
              "rasterize_forward: float32 inputs and int32 radii expected");
  means2d = means2d.contiguous(); conics = conics.contiguous(); opacities = opacities.contiguous();
  colors = colors.contiguous(); radii = radii.contiguous(); depths = depths.contiguous();
  const int64_t n = means2d.size(0), C = colors.size(1);
  const int W = int(width), H = int(height), TS = int(tile);
  const int tiles_x = (W + TS - 1) / TS;
  Binning bins = bin_tiles(means2d.data_ptr<float>(), radii.data_ptr<int32_t>(), depths.data_ptr<float>(), n, W,
                           H, TS);
  const int64_t n_tiles = int64_t(bins.offsets.size()) - 1;

  // Outputs start uninitialised (NaN / garbage ids when `poison`, for tests): every element is
  // written below, empty tiles included.
  auto out = torch::empty({H, W, C}, colors.options());
  auto t_final = torch::empty({H, W}, colors.options());
  auto n_contrib = torch::empty({H, W}, radii.options());
  auto max_id = torch::empty({H, W}, radii.options());
  if (poison) {
    out.fill_(NAN); t_final.fill_(NAN); n_contrib.fill_(-7); max_id.fill_(-7);
  }
  const float* m2 = means2d.data_ptr<float>();
  const float* cn = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  float* out_p = out.data_ptr<float>();
  float* tf_p = t_final.data_ptr<float>();
  int32_t* nc_p = n_contrib.data_ptr<int32_t>();
  int32_t* id_p = max_id.data_ptr<int32_t>();

#pragma omp parallel
  {
    TileData td;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = bins.offsets[t], k = bins.offsets[t + 1] - s;
      const int32_t* ids = bins.gids.data() + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      for (int py = ty * TS; py < std::min((ty + 1) * TS, H); ++py) {
        for (int px = tx * TS; px < std::min((tx + 1) * TS, W); ++px) {
          const float fx = float(px), fy = float(py);
          float T = 1.0f, best_w = 0.0f;
          int32_t best = -1, last = 0;
          float* o_pix = out_p + (int64_t(py) * W + px) * C;
          std::fill(o_pix, o_pix + C, 0.0f);
          for (int64_t j = 0; j < k; ++j) {
            const float dx = td.u[j] - fx, dy = td.v[j] - fy;
            const float power = -0.5f * (td.a[j] * dx * dx + td.c[j] * dy * dy) - td.b[j] * dx * dy;
            if (power > 0.0f || power < td.thr[j]) continue;
            const float alpha = std::min(kAlphaMax, td.o[j] * std::exp(power));
            if (alpha < kAlphaMin) continue;
            const float next_T = T * (1.0f - alpha);
            if (next_T < kTMin) break;
            const float w = alpha * T;
            const float* cg = col + int64_t(ids[j]) * C;
            for (int64_t ch = 0; ch < C; ++ch) o_pix[ch] += w * cg[ch];
            if (w > best_w) { best_w = w; best = ids[j]; }
            T = next_T;
            last = int32_t(j + 1);
          }
          tf_p[int64_t(py) * W + px] = T;
          nc_p[int64_t(py) * W + px] = last;
          id_p[int64_t(py) * W + px] = best;
        }
      }
    }
  }
  auto offsets = torch::from_blob(bins.offsets.data(), {n_tiles + 1}, torch::kInt64).clone();
  auto gids = torch::from_blob(bins.gids.data(), {int64_t(bins.gids.size())}, torch::kInt32).clone();
  return {out, t_final, n_contrib, max_id, offsets, gids};
}

// Gradients w.r.t. means2d [N, 2], conics [N, 3], opacities [N], colors [N, C], given dL/dcolour
// [H, W, C] and dL/d(accumulated alpha) [H, W]. Walks each pixel's list back to front.
std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor conics,
                                              torch::Tensor opacities, torch::Tensor colors,
                                              torch::Tensor offsets, torch::Tensor gids,
                                              torch::Tensor t_final, torch::Tensor n_contrib,
                                              torch::Tensor grad_out, torch::Tensor grad_alpha,
                                              int64_t width, int64_t height, int64_t tile, bool poison) {
  means2d = means2d.contiguous(); conics = conics.contiguous(); opacities = opacities.contiguous();
  colors = colors.contiguous(); grad_out = grad_out.contiguous(); grad_alpha = grad_alpha.contiguous();
  const int64_t n = means2d.size(0), C = colors.size(1);
  const int W = int(width), H = int(height), TS = int(tile);
  const int tiles_x = (W + TS - 1) / TS;
  const int64_t n_tiles = offsets.size(0) - 1;
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* gid = gids.data_ptr<int32_t>();
  const float* m2 = means2d.data_ptr<float>();
  const float* cn = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  const float* tf = t_final.data_ptr<float>();
  const int32_t* nc = n_contrib.data_ptr<int32_t>();
  const float* go = grad_out.data_ptr<float>();
  const float* ga = grad_alpha.data_ptr<float>();

  // One gradient buffer per thread, summed in thread order: no atomics, deterministic for a fixed
  // thread count. Layout per Gaussian: [du, dv, da, db, dc, do, dcolor x C].
  const int nt = num_threads();
  const int64_t stride = 6 + C;
  std::vector<std::vector<float>> bufs(nt);

#pragma omp parallel
  {
    std::vector<float>& g = bufs[thread_id()];
    g.assign(n * stride, 0.0f);
    TileData td;
    std::vector<float> S(C);
#pragma omp for schedule(static, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t s = off[t], k = off[t + 1] - s;
      if (k == 0) continue;
      const int32_t* ids = gid + s;
      td.load(ids, k, m2, cn, op);
      const int ty = int(t / tiles_x), tx = int(t % tiles_x);
      for (int py = ty * TS; py < std::min((ty + 1) * TS, H); ++py) {
        for (int px = tx * TS; px < std::min((tx + 1) * TS, W); ++px) {
          const int64_t pix = int64_t(py) * W + px;
          const float fx = float(px), fy = float(py);
          const float T_fin = tf[pix];
          const float* gout = go + pix * C;
          const float galpha = ga[pix];
          std::fill(S.begin(), S.end(), 0.0f);  // sum over Gaussians behind: c_j alpha_j T_j
          float T = T_fin;
          for (int64_t j = int64_t(nc[pix]) - 1; j >= 0; --j) {
            const float dx = td.u[j] - fx, dy = td.v[j] - fy;
            const float power = -0.5f * (td.a[j] * dx * dx + td.c[j] * dy * dy) - td.b[j] * dx * dy;
            if (power > 0.0f || power < td.thr[j]) continue;
            const float vis = std::exp(power);
            const float raw = td.o[j] * vis;
            const float alpha = std::min(kAlphaMax, raw);
            if (alpha < kAlphaMin) continue;
            const float inv = 1.0f / (1.0f - alpha);
            T *= inv;  // transmittance in front of Gaussian j
            const float w = alpha * T;
            const int32_t gi = ids[j];
            const float* cg = col + int64_t(gi) * C;
            float* gb = g.data() + int64_t(gi) * stride;
            float dL_dalpha = galpha * T_fin * inv;
            for (int64_t ch = 0; ch < C; ++ch) {
              gb[6 + ch] += w * gout[ch];
              dL_dalpha += gout[ch] * (T * cg[ch] - S[ch] * inv);
              S[ch] += w * cg[ch];
            }
            if (raw > kAlphaMax) continue;  // clamped alpha: no gradient to opacity or shape
            const float dL_dpower = dL_dalpha * alpha;
            gb[5] += dL_dalpha * vis;
            gb[2] += dL_dpower * (-0.5f * dx * dx);
            gb[3] += dL_dpower * (-dx * dy);
            gb[4] += dL_dpower * (-0.5f * dy * dy);
            gb[0] += dL_dpower * (-(td.a[j] * dx + td.b[j] * dy));
            gb[1] += dL_dpower * (-(td.c[j] * dy + td.b[j] * dx));
          }
        }
      }
    }
  }
  auto total = torch::empty({n, stride}, colors.options());
  if (poison) total.fill_(NAN);
  float* tp = total.data_ptr<float>();
  bool first = true;
  for (int i = 0; i < nt; ++i) {
    if (bufs[i].size() != size_t(n * stride)) continue;  // a thread the runtime did not start
    const float* b = bufs[i].data();
    const bool assign = first;
#pragma omp parallel for schedule(static)
    for (int64_t e = 0; e < n * stride; ++e) tp[e] = assign ? b[e] : tp[e] + b[e];
    first = false;
  }
  if (first) total.zero_();
  return {total.slice(1, 0, 2).contiguous(), total.slice(1, 2, 5).contiguous(), total.select(1, 5).contiguous(),
          total.slice(1, 6, stride).contiguous()};
}

// project_cpu.cpp
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                           torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                           int64_t width, int64_t height, double near, double far, double eps2d);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                            torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                            int64_t width, int64_t height, double near, double far, double eps2d,
                                            torch::Tensor g_means2d, torch::Tensor g_conics, torch::Tensor g_depths,
                                            torch::Tensor g_opac);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "EWA projection forward (CPU)");
  m.def("project_backward", &project_backward, "EWA projection backward (CPU)");
  m.def("rasterize_forward", &rasterize_forward, "Gaussian rasterization forward (CPU)");
  m.def("rasterize_backward", &rasterize_backward, "Gaussian rasterization backward (CPU)");
}
