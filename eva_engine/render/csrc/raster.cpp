// Compiled CPU kernels of eva_engine.render: EWA projection, tile binning, tile compositing and
// SH colours, each forward with a hand-written backward (binning has none). Built on first use by eva_engine/render/native.py; the pure-torch
// kernels in tiles.py and composite.py follow the same rules and stay the fallback.
//
// Rules (3DGS / gsplat "classic", as in composite.py): alpha = min(0.999, o exp(power)) with
// power = -1/2 d^T conic d, d = mean - pixel centre; pairs with alpha < 1/255 are skipped; a
// pixel stops before the Gaussian that would take its transmittance to <= 1e-4.
//
// Layout: tiles are row-major (tile = ty * tiles_x + tx), P = tile_size^2 pixels per tile,
// row-major inside the tile, pixel centres at (x + 0.5, y + 0.5). Each tile is processed by
// one thread with its P pixels as the innermost (vectorised) loop, so nothing per Gaussian-pixel
// pair is ever stored.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <omp.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <tuple>
#include <vector>

namespace {

constexpr double kAlphaMax = 0.999;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;

// exp() that the compiler can vectorise (glibc's expf is a scalar call that blocks it):
// Cephes' expf, relative error < 2e-7 on the clamped range. double keeps std::exp (float64 is
// for gradient checks, where accuracy matters more than speed).
inline float exp_vec(float x) {
  x = std::min(std::max(x, -87.0f), 88.0f);
  const float fx = std::floor(x * 1.44269504088896341f + 0.5f);
  const float r = x - fx * 0.693359375f + fx * 2.12194440e-4f;
  float y = 1.9875691500e-4f;
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  y = y * r * r + r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(fx) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof scale);  // 2^fx
  return y * scale;
}

inline double exp_vec(double x) { return std::exp(x); }

int num_threads() { return std::max(1, at::get_num_threads()); }

// Tiles, longest lists first: with dynamic scheduling the expensive tiles start early and the
// cheap ones fill the gaps at the end.
std::vector<int64_t> tiles_by_work(const int64_t* count, int64_t n_tiles) {
  std::vector<int64_t> order(n_tiles);
  std::iota(order.begin(), order.end(), int64_t(0));
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return count[a] > count[b]; });
  return order;
}

// Tile geometry of an image: tile = ty * tiles_x + tx of ts x ts pixels, the last row and column
// of tiles possibly partly outside the width x height image.
struct Frame {
  int64_t tiles_x, ts, width, height;
  int64_t x0(int64_t tile) const { return (tile % tiles_x) * ts; }
  int64_t y0(int64_t tile) const { return (tile / tiles_x) * ts; }
  // Image pixel index of tile pixel p, or -1 outside the image.
  int64_t pixel(int64_t tile, int64_t p) const {
    const int64_t x = x0(tile) + p % ts, y = y0(tile) + p / ts;
    return (x < width && y < height) ? y * width + x : -1;
  }
};

template <typename scalar_t>
struct Gaussian2d {
  scalar_t mx, my, a, b, c, o;  // tile-local mean, conic, opacity
};

template <typename scalar_t>
inline Gaussian2d<scalar_t> load_gaussian(const scalar_t* means, const scalar_t* conics, const scalar_t* opac,
                                          int64_t g, scalar_t x0, scalar_t y0) {
  return {means[2 * g] - x0, means[2 * g + 1] - y0, conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], opac[g]};
}

// Per-thread scratch of one tile, structure of arrays so the pixel loops vectorise.
template <typename scalar_t>
struct TileScratch {
  std::vector<scalar_t> px, py, T, aux, h, w, feat;  // feat: [F, P]
  std::vector<int32_t> cnt;
  TileScratch(int64_t ts, int64_t F)
      : px(ts * ts), py(ts * ts), T(ts * ts), aux(ts * ts), h(ts * ts), w(ts * ts), feat(F * ts * ts),
        cnt(ts * ts) {
    for (int64_t p = 0; p < ts * ts; ++p) {
      px[p] = static_cast<scalar_t>(p % ts) + scalar_t(0.5);
      py[p] = static_cast<scalar_t>(p / ts) + scalar_t(0.5);
    }
  }
};

// ------------------------------------------------------------------------------ compositing

// One Gaussian over the P pixels of a tile, front to back. T: transmittance; done: 1 once the
// pixel has stopped; w: out, the blend weights alpha T (0 where not blended). Returns the number
// of stopped pixels.
template <typename scalar_t>
scalar_t blend_step(const Gaussian2d<scalar_t> G, int32_t position, int64_t P, const scalar_t* __restrict px,
                    const scalar_t* __restrict py, scalar_t* __restrict T, scalar_t* __restrict done,
                    scalar_t* __restrict w, int32_t* __restrict cnt) {
  const scalar_t amax = kAlphaMax, amin = kAlphaMin, tmin = kTMin;
  scalar_t n_done = 0;
#pragma omp simd reduction(+ : n_done)
  for (int64_t p = 0; p < P; ++p) {
    const scalar_t dx = G.mx - px[p], dy = G.my - py[p];
    const scalar_t power = scalar_t(-0.5) * (G.a * dx * dx + G.c * dy * dy) - G.b * dx * dy;
    const scalar_t raw = G.o * exp_vec(power);
    const scalar_t alpha = std::min(amax, raw);
    const scalar_t t = T[p];
    const scalar_t t_next = t * (scalar_t(1) - alpha);
    // 0/1 masks as floats and selects that yield floats: GCC vectorises these, not bool logic.
    const scalar_t visible = raw >= amin ? scalar_t(1) - done[p] : scalar_t(0);
    const scalar_t stop = t_next <= tmin ? visible : scalar_t(0);
    const scalar_t use = visible - stop;
    w[p] = use * alpha * t;
    T[p] = use > scalar_t(0) ? t_next : t;
    cnt[p] = use > scalar_t(0) ? position + 1 : cnt[p];
    done[p] += stop;
    n_done += done[p];
  }
  return n_done;
}

// acc[c, p] += w[p] * f[c]
template <typename scalar_t>
void accumulate(const scalar_t* __restrict f, int64_t F, int64_t P, const scalar_t* __restrict w,
                scalar_t* __restrict acc) {
  for (int64_t c = 0; c < F; ++c) {
    const scalar_t fc = f[c];
#pragma omp simd
    for (int64_t p = 0; p < P; ++p) acc[c * P + p] += w[p] * fc;
  }
}

// Per-Gaussian features: D colour channels, then the camera depth.
template <typename scalar_t>
inline void load_features(const scalar_t* colors, const scalar_t* depths, int64_t D, int64_t g, scalar_t* f) {
  for (int64_t c = 0; c < D; ++c) f[c] = colors[g * D + c];
  f[D] = depths[g];
}

template <typename scalar_t>
struct Scene {
  const scalar_t *means, *conics, *opac, *colors, *depths, *background;
  int64_t D;
  const int64_t *gids, *tstart, *tcount;
  int64_t n_tiles;
};

// Writes image [H, W, D] = sum_i alpha_i T_i c_i + T_final * background, depth [H, W],
// alpha [H, W] = 1 - T_final, and for the backward pass T_final [H, W] and the per-pixel count
// [H, W] of list entries up to and including the last one blended.
template <typename scalar_t>
void forward_kernel(const Scene<scalar_t>& sc, const Frame& fr, scalar_t* image, scalar_t* depth, scalar_t* alpha,
                    scalar_t* t_out, int32_t* cnt_out) {
  const int64_t P = fr.ts * fr.ts, D = sc.D, F = D + 1;
  const std::vector<int64_t> order = tiles_by_work(sc.tcount, sc.n_tiles);
#pragma omp parallel num_threads(num_threads())
  {
    TileScratch<scalar_t> s(fr.ts, F);
    std::vector<scalar_t> f(F);
#pragma omp for schedule(dynamic, 1)
    for (int64_t k = 0; k < sc.n_tiles; ++k) {
      const int64_t tile = order[k];
      const scalar_t x0 = static_cast<scalar_t>(fr.x0(tile)), y0 = static_cast<scalar_t>(fr.y0(tile));
      std::fill(s.T.begin(), s.T.end(), scalar_t(1));
      std::fill(s.aux.begin(), s.aux.end(), scalar_t(0));  // done flags
      std::fill(s.feat.begin(), s.feat.end(), scalar_t(0));  // accumulated features [F, P]
      std::fill(s.cnt.begin(), s.cnt.end(), 0);
      const int64_t start = sc.tstart[tile], n = sc.tcount[tile];
      for (int64_t j = 0; j < n; ++j) {
        const int64_t g = sc.gids[start + j];
        const scalar_t n_done =
            blend_step(load_gaussian(sc.means, sc.conics, sc.opac, g, x0, y0), static_cast<int32_t>(j), P,
                       s.px.data(), s.py.data(), s.T.data(), s.aux.data(), s.w.data(), s.cnt.data());
        load_features(sc.colors, sc.depths, D, g, f.data());
        accumulate(f.data(), F, P, s.w.data(), s.feat.data());
        if (n_done == static_cast<scalar_t>(P)) break;  // every pixel of the tile has stopped
      }
      for (int64_t p = 0; p < P; ++p) {
        const int64_t i = fr.pixel(tile, p);
        if (i < 0) continue;
        const scalar_t t = s.T[p];
        for (int64_t c = 0; c < D; ++c) image[i * D + c] = s.feat[c * P + p] + t * sc.background[c];
        depth[i] = s.feat[D * P + p];
        alpha[i] = scalar_t(1) - t;
        t_out[i] = t;
        cnt_out[i] = s.cnt[p];
      }
    }
  }
}

struct GaussianGrad {
  double mx, my, a, b, c, o;
};

// One Gaussian (list position ``position``) over the P pixels of a tile, back to front. T: the
// transmittance behind it, updated to the one in front of it; S: G_{i+1}, updated to G_i;
// h: dL/dacc . f; w: out, the blend weights. Returns dL/d(mean, conic, opacity) of the pair.
template <typename scalar_t>
GaussianGrad unblend_step(const Gaussian2d<scalar_t> G, int32_t position, int64_t P,
                          const scalar_t* __restrict px, const scalar_t* __restrict py,
                          const int32_t* __restrict cnt, const scalar_t* __restrict h, scalar_t* __restrict T,
                          scalar_t* __restrict S, scalar_t* __restrict w) {
  const scalar_t amax = kAlphaMax, amin = kAlphaMin;
  scalar_t g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_o = 0;
#pragma omp simd reduction(+ : g_mx, g_my, g_a, g_b, g_c, g_o)
  for (int64_t p = 0; p < P; ++p) {
    const scalar_t dx = G.mx - px[p], dy = G.my - py[p];
    const scalar_t power = scalar_t(-0.5) * (G.a * dx * dx + G.c * dy * dy) - G.b * dx * dy;
    const scalar_t e = exp_vec(power);
    const scalar_t raw = G.o * e;
    const scalar_t alpha = std::min(amax, raw);
    // alpha where the forward pass blended this pair, else 0 (as a float select: see blend_step).
    const scalar_t alpha_used = position < cnt[p] ? (raw >= amin ? alpha : scalar_t(0)) : scalar_t(0);
    const scalar_t inv_one_minus = scalar_t(1) / (scalar_t(1) - alpha);
    const scalar_t t_before = T[p] * inv_one_minus;
    const scalar_t weight = alpha_used * t_before;
    const scalar_t s = S[p] + weight * h[p];
    // Zero where alpha is clamped at 0.999 (min() passes no gradient there).
    const scalar_t alpha_free = raw < amax ? alpha_used : scalar_t(0);
    const scalar_t d_alpha = alpha_free > scalar_t(0) ? (t_before * h[p] - s) * inv_one_minus : scalar_t(0);
    const scalar_t d_power = d_alpha * raw;
    g_mx -= d_power * (G.a * dx + G.b * dy);
    g_my -= d_power * (G.b * dx + G.c * dy);
    g_a -= scalar_t(0.5) * d_power * dx * dx;
    g_b -= d_power * dx * dy;
    g_c -= scalar_t(0.5) * d_power * dy * dy;
    g_o += d_alpha * e;
    S[p] = s;
    T[p] = alpha_used > scalar_t(0) ? t_before : T[p];
    w[p] = weight;
  }
  return {g_mx, g_my, g_a, g_b, g_c, g_o};
}

// h[p] = sum_c f[c] gacc[c, p]
template <typename scalar_t>
void project_grad(const scalar_t* __restrict f, int64_t F, int64_t P, const scalar_t* __restrict gacc,
                  scalar_t* __restrict h) {
#pragma omp simd
  for (int64_t p = 0; p < P; ++p) h[p] = f[0] * gacc[p];
  for (int64_t c = 1; c < F; ++c) {
    const scalar_t fc = f[c];
#pragma omp simd
    for (int64_t p = 0; p < P; ++p) h[p] += fc * gacc[c * P + p];
  }
}

// Per pixel, with T_i the transmittance in front of Gaussian i, h_i = dL/dacc . f_i and
// G_i = sum_{j>=i} alpha_j T_j h_j + dL/dT_final * T_final:
//     dL/dalpha_i = (T_i h_i - G_i) / (1 - alpha_i),   dL/df_i = alpha_i T_i dL/dacc,
// walking each pixel's list back to front from its last blended entry and recovering
// T_i = T_{i+1} / (1 - alpha_i) from the saved final transmittance. Gradients per intersection
// (rows [M, 7 + D]: mean x, y, conic a, b, c, opacity, colours, depth) are written by the tile's
// thread and summed per Gaussian afterwards in a fixed order, so results are deterministic;
// bg_rows [T, D] gets each tile's sum of dL/dimage * T_final (the background's gradient).
template <typename scalar_t>
void backward_kernel(const Scene<scalar_t>& sc, const Frame& fr, const scalar_t* t_final, const int32_t* cnt_in,
                     const scalar_t* grad_image, const scalar_t* grad_depth, const scalar_t* grad_alpha,
                     scalar_t* rows, scalar_t* bg_rows) {
  const int64_t P = fr.ts * fr.ts, D = sc.D, F = D + 1, R = 6 + F;
  const std::vector<int64_t> order = tiles_by_work(sc.tcount, sc.n_tiles);
#pragma omp parallel num_threads(num_threads())
  {
    TileScratch<scalar_t> s(fr.ts, F);
    std::vector<scalar_t> f(F);
#pragma omp for schedule(dynamic, 1)
    for (int64_t k = 0; k < sc.n_tiles; ++k) {
      const int64_t tile = order[k];
      const scalar_t x0 = static_cast<scalar_t>(fr.x0(tile)), y0 = static_cast<scalar_t>(fr.y0(tile));
      int32_t last = 0;
      scalar_t* bg = bg_rows + tile * D;
      std::fill(bg, bg + D, scalar_t(0));
      for (int64_t p = 0; p < P; ++p) {
        const int64_t i = fr.pixel(tile, p);
        if (i < 0) {  // outside the image: no loss, nothing to walk
          s.T[p] = 1;
          s.aux[p] = 0;
          s.cnt[p] = 0;
          for (int64_t c = 0; c < F; ++c) s.feat[c * P + p] = 0;
          continue;
        }
        const scalar_t t = t_final[i];
        scalar_t d_t = -grad_alpha[i];  // dL/dT_final
        for (int64_t c = 0; c < D; ++c) {
          const scalar_t g = grad_image[i * D + c];
          s.feat[c * P + p] = g;
          d_t += g * sc.background[c];
          bg[c] += g * t;
        }
        s.feat[D * P + p] = grad_depth[i];
        s.T[p] = t;
        s.aux[p] = d_t * t;  // S = G_n: everything behind the last Gaussian
        s.cnt[p] = cnt_in[i];
        last = std::max(last, s.cnt[p]);
      }
      const int64_t start = sc.tstart[tile], n = sc.tcount[tile];
      // Entries no pixel reached get zero gradients.
      std::fill(rows + (start + std::min<int64_t>(last, n)) * R, rows + (start + n) * R, scalar_t(0));
      for (int64_t j = std::min<int64_t>(last, n) - 1; j >= 0; --j) {
        const int64_t g = sc.gids[start + j];
        load_features(sc.colors, sc.depths, D, g, f.data());
        project_grad(f.data(), F, P, s.feat.data(), s.h.data());
        const GaussianGrad d = unblend_step(load_gaussian(sc.means, sc.conics, sc.opac, g, x0, y0),
                                            static_cast<int32_t>(j), P, s.px.data(), s.py.data(), s.cnt.data(),
                                            s.h.data(), s.T.data(), s.aux.data(), s.w.data());
        scalar_t* row = rows + (start + j) * R;
        row[0] = d.mx;
        row[1] = d.my;
        row[2] = d.a;
        row[3] = d.b;
        row[4] = d.c;
        row[5] = d.o;
        const scalar_t* w = s.w.data();
        for (int64_t c = 0; c < F; ++c) {
          const scalar_t* gc = s.feat.data() + c * P;
          scalar_t sum = 0;
#pragma omp simd reduction(+ : sum)
          for (int64_t p = 0; p < P; ++p) sum += w[p] * gc[p];
          row[6 + c] = sum;
        }
      }
    }
  }
}

// ------------------------------------------------------------------------------ operators

// Inputs of both compositing operators, checked and made contiguous.
struct CompositeInputs {
  at::Tensor means2d, conics, opacities, colors, depths, background, gids, tstart, tcount;
  Frame frame;

  CompositeInputs(const at::Tensor& means2d_, const at::Tensor& conics_, const at::Tensor& opacities_,
                  const at::Tensor& colors_, const at::Tensor& depths_, const at::Tensor& background_,
                  const at::Tensor& gauss_ids, const at::Tensor& tile_start, const at::Tensor& tile_count,
                  int64_t tiles_x, int64_t tile_size, int64_t width, int64_t height)
      : frame{tiles_x, tile_size, width, height} {
    TORCH_CHECK(means2d_.device().is_cpu(), "eva_raster kernels run on the CPU");
    TORCH_CHECK(means2d_.dim() == 2 && means2d_.size(1) == 2, "means2d must be [N, 2]");
    const int64_t n = means2d_.size(0);
    TORCH_CHECK(conics_.sizes() == at::IntArrayRef({n, 3}), "conics must be [N, 3]");
    TORCH_CHECK(opacities_.sizes() == at::IntArrayRef({n}), "opacities must be [N]");
    TORCH_CHECK(colors_.dim() == 2 && colors_.size(0) == n && colors_.size(1) >= 1, "colors must be [N, D]");
    TORCH_CHECK(depths_.sizes() == at::IntArrayRef({n}), "depths must be [N]");
    TORCH_CHECK(background_.sizes() == at::IntArrayRef({colors_.size(1)}), "background must be [D]");
    for (const auto* t : {&conics_, &opacities_, &colors_, &depths_, &background_})
      TORCH_CHECK(t->scalar_type() == means2d_.scalar_type() && t->device().is_cpu(),
                  "all float inputs must share one dtype, on the CPU");
    for (const auto* t : {&gauss_ids, &tile_start, &tile_count})
      TORCH_CHECK(t->scalar_type() == at::kLong && t->dim() == 1, "tile arrays must be 1-D int64");
    TORCH_CHECK(tile_size >= 1 && tiles_x >= 1 && width >= 1 && height >= 1, "bad image or tile geometry");
    TORCH_CHECK(tiles_x * tile_size >= width && tile_start.size(0) % tiles_x == 0 &&
                    (tile_start.size(0) / tiles_x) * tile_size >= height && tile_count.size(0) == tile_start.size(0),
                "tile arrays do not cover the image");
    means2d = means2d_.contiguous();
    conics = conics_.contiguous();
    opacities = opacities_.contiguous();
    colors = colors_.contiguous();
    depths = depths_.contiguous();
    background = background_.contiguous();
    gids = gauss_ids.contiguous();
    tstart = tile_start.contiguous();
    tcount = tile_count.contiguous();
  }

  int64_t D() const { return colors.size(1); }

  template <typename scalar_t>
  Scene<scalar_t> scene() const {
    return {means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(),
            colors.data_ptr<scalar_t>(),  depths.data_ptr<scalar_t>(), background.data_ptr<scalar_t>(),
            D(),
            gids.data_ptr<int64_t>(),     tstart.data_ptr<int64_t>(),  tcount.data_ptr<int64_t>(),
            tstart.size(0)};
  }
};

// Returns image [H, W, D] (over the background), depth [H, W, 1], alpha [H, W, 1], and for the
// backward pass T_final [H, W] and count [H, W] (int32).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite_image_forward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
    const at::Tensor& depths, const at::Tensor& background, const at::Tensor& gauss_ids, const at::Tensor& tile_start,
    const at::Tensor& tile_count, int64_t tiles_x, int64_t tile_size, int64_t width, int64_t height) {
  const CompositeInputs in(means2d, conics, opacities, colors, depths, background, gauss_ids, tile_start, tile_count,
                           tiles_x, tile_size, width, height);
  const auto opt = in.means2d.options();
  auto image = at::empty({height, width, in.D()}, opt);
  auto depth = at::empty({height, width, 1}, opt);
  auto alpha = at::empty({height, width, 1}, opt);
  auto t_final = at::empty({height, width}, opt);
  auto count = at::empty({height, width}, opt.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(in.means2d.scalar_type(), "eva_raster_composite_forward", [&] {
    forward_kernel<scalar_t>(in.scene<scalar_t>(), in.frame, image.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                             alpha.data_ptr<scalar_t>(), t_final.data_ptr<scalar_t>(), count.data_ptr<int32_t>());
  });
  return {image, depth, alpha, t_final, count};
}

// Returns dL/d(means2d [N, 2], conics [N, 3], opacities [N], colors [N, D], depths [N]) packed as
// [N, 7 + D], and dL/dbackground [D].
std::tuple<at::Tensor, at::Tensor> composite_image_backward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
    const at::Tensor& depths, const at::Tensor& background, const at::Tensor& gauss_ids, const at::Tensor& tile_start,
    const at::Tensor& tile_count, int64_t tiles_x, int64_t tile_size, int64_t width, int64_t height,
    const at::Tensor& t_final, const at::Tensor& count, const at::Tensor& grad_image, const at::Tensor& grad_depth,
    const at::Tensor& grad_alpha) {
  const CompositeInputs in(means2d, conics, opacities, colors, depths, background, gauss_ids, tile_start, tile_count,
                           tiles_x, tile_size, width, height);
  const int64_t D = in.D(), N = in.means2d.size(0), M = in.gids.size(0), R = 7 + D, T = in.tstart.size(0);
  const auto dt = in.means2d.scalar_type();
  TORCH_CHECK(t_final.sizes() == at::IntArrayRef({height, width}), "t_final must be [H, W]");
  TORCH_CHECK(count.sizes() == at::IntArrayRef({height, width}) && count.scalar_type() == at::kInt,
              "count must be int32 [H, W]");
  TORCH_CHECK(grad_image.sizes() == at::IntArrayRef({height, width, D}), "grad_image must be [H, W, D]");
  TORCH_CHECK(grad_depth.numel() == height * width && grad_alpha.numel() == height * width,
              "grad_depth and grad_alpha must be [H, W, 1]");
  const auto tf = t_final.contiguous().to(dt), ct = count.contiguous();
  const auto gi = grad_image.contiguous().to(dt), gd = grad_depth.contiguous().to(dt);
  const auto ga = grad_alpha.contiguous().to(dt);
  auto rows = at::empty({M, R}, in.means2d.options());
  auto bg_rows = at::empty({T, D}, in.means2d.options());
  auto out = at::zeros({N, R}, in.means2d.options());
  auto grad_bg = at::zeros({D}, in.means2d.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "eva_raster_composite_backward", [&] {
    backward_kernel<scalar_t>(in.scene<scalar_t>(), in.frame, tf.data_ptr<scalar_t>(), ct.data_ptr<int32_t>(),
                              gi.data_ptr<scalar_t>(), gd.data_ptr<scalar_t>(), ga.data_ptr<scalar_t>(),
                              rows.data_ptr<scalar_t>(), bg_rows.data_ptr<scalar_t>());
    // The scatter onto Gaussians and the background sum, in a fixed order: the same on every run.
    const scalar_t* r = rows.data_ptr<scalar_t>();
    const int64_t* ids = in.gids.data_ptr<int64_t>();
    scalar_t* dst = out.data_ptr<scalar_t>();
    for (int64_t i = 0; i < M; ++i) {
      scalar_t* d = dst + ids[i] * R;
      const scalar_t* src = r + i * R;
      for (int64_t c = 0; c < R; ++c) d[c] += src[c];
    }
    const scalar_t* b = bg_rows.data_ptr<scalar_t>();
    scalar_t* gb = grad_bg.data_ptr<scalar_t>();
    for (int64_t t = 0; t < T; ++t)
      for (int64_t c = 0; c < D; ++c) gb[c] += b[t * D + c];
  });
  return {out, grad_bg};
}

// ------------------------------------------------------------------------------ binning

// Tile-local test (in double) that a Gaussian reaches alpha >= 1/255 at some in-image pixel
// centre of tile (tx, ty): the same maths and slack as tiles.py's _reaches_tile. -q/2 is concave,
// so over the rectangle of pixel centres it peaks at the mean when the mean is inside, and
// otherwise on an edge, at the clamped 1D optimum.
inline bool reaches_tile(double mx, double my, double a, double b, double c, double log_thresh, int64_t tx,
                         int64_t ty, int64_t ts, int64_t width, int64_t height) {
  mx -= static_cast<double>(tx * ts);
  my -= static_cast<double>(ty * ts);
  const double lo = 0.5;
  const double hx = std::min(static_cast<double>(width - tx * ts) - 0.5, ts - 0.5);
  const double hy = std::min(static_cast<double>(height - ty * ts) - 0.5, ts - 0.5);
  const bool inside = mx >= lo && mx <= hx && my >= lo && my <= hy;
  double best = 0.0;
  if (!inside) {
    auto value = [&](double x, double y) {
      const double dx = mx - x, dy = my - y;
      return -0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy);
    };
    auto clip = [&](double v, double high) { return std::min(std::max(v, lo), high); };
    best = std::max(value(lo, clip(my + b * (mx - lo) / c, hy)), value(hx, clip(my + b * (mx - hx) / c, hy)));
    best = std::max(best, value(clip(mx + b * (my - lo) / a, hx), lo));
    best = std::max(best, value(clip(mx + b * (my - hy) / a, hx), hy));
  }
  const double reach = std::max(std::max(std::abs(mx - lo), std::abs(mx - hx)),
                                std::max(std::abs(my - lo), std::abs(my - hy)));
  const double slack = 1e-3 + 1e-5 * (a + 2 * std::abs(b) + c) * reach * reach;
  return best >= log_thresh - slack;
}

struct Box {
  int64_t x0, x1, y0, y1;
};

// Candidate tiles of one Gaussian: the projection's bounding box, shrunk to the ellipse where
// o exp(-q/2) >= 1/255 (gsplat's opacity-aware extent, sqrt(2 log(255 o)) sigmas per axis).
// The exact test decides; a tighter box only saves candidates.
template <typename scalar_t>
Box candidate_box(const scalar_t* means, const scalar_t* conics, const scalar_t* opac, const int32_t* radii,
                  int64_t g, int64_t ts, int64_t tiles_x, int64_t tiles_y) {
  const double mx = means[2 * g], my = means[2 * g + 1];
  double rx = radii[2 * g], ry = radii[2 * g + 1];
  const double a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
  const double o = opac[g];
  const double det = a * c - b * b;
  if (!(o * 255.0 > 1.0)) return {0, 0, 0, 0};  // alpha < 1/255 everywhere
  if (det > 0 && std::isfinite(det)) {
    const double q = 2.0 * std::log(o * 255.0);
    // +1 px: rounding of the conic (float32) must never shrink the box below the true extent.
    rx = std::min(rx, std::sqrt(q * c / det) + 1.0);
    ry = std::min(ry, std::sqrt(q * a / det) + 1.0);
  }
  auto clampi = [](double v, int64_t hi) { return static_cast<int64_t>(std::min<double>(std::max(v, 0.0), hi)); };
  return {clampi(std::floor((mx - rx) / ts), tiles_x), clampi(std::ceil((mx + rx) / ts), tiles_x),
          clampi(std::floor((my - ry) / ts), tiles_y), clampi(std::ceil((my + ry) / ts), tiles_y)};
}

struct BinGeometry {
  int64_t ts, tiles_x, tiles_y, width, height;
};

// The number of candidate tiles of each of Gaussians ids[0..V), to count[v].
template <typename scalar_t>
void candidate_counts(const scalar_t* mp, const scalar_t* cp, const scalar_t* op, const int32_t* r,
                      const int64_t* ids, int64_t V, const BinGeometry& geo, int64_t* count) {
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t v = 0; v < V; ++v) {
    const Box box = candidate_box(mp, cp, op, r, ids[v], geo.ts, geo.tiles_x, geo.tiles_y);
    count[v] = (box.x1 - box.x0) * (box.y1 - box.y0);
  }
}

// The exact test over the candidate tiles of Gaussians ids[0..V): the tiles Gaussian v reaches
// go to pair_tile[offs[v]...], and their number to kept[v].
template <typename scalar_t>
void bin_pass(const scalar_t* mp, const scalar_t* cp, const scalar_t* op, const int32_t* r, const int64_t* ids,
              int64_t V, const BinGeometry& geo, const int64_t* offs, int64_t* kept, int32_t* pair_tile) {
#pragma omp parallel for schedule(dynamic, 256) num_threads(num_threads())
  for (int64_t v = 0; v < V; ++v) {
    const int64_t g = ids[v];
    const Box box = candidate_box(mp, cp, op, r, g, geo.ts, geo.tiles_x, geo.tiles_y);
    const double log_thresh = std::log(1.0 / 255.0) - std::log(std::max<double>(op[g], 1e-30));
    int32_t* out = pair_tile + offs[v];
    int64_t n = 0;
    for (int64_t ty = box.y0; ty < box.y1; ++ty)
      for (int64_t tx = box.x0; tx < box.x1; ++tx)
        if (reaches_tile(mp[2 * g], mp[2 * g + 1], cp[3 * g], cp[3 * g + 1], cp[3 * g + 2], log_thresh, tx, ty,
                         geo.ts, geo.width, geo.height))
          out[n++] = static_cast<int32_t>(ty * geo.tiles_x + tx);
    kept[v] = n;
  }
}

// Visible Gaussians (both radii > 0) front to back: by camera depth, ties by index (the same
// order as a stable argsort), by a comparison sort.
template <typename scalar_t>
std::vector<int64_t> compared_depth_order(const int32_t* radii, const scalar_t* depths, int64_t N) {
  std::vector<int64_t> order;
  order.reserve(N);
  for (int64_t g = 0; g < N; ++g)
    if (radii[2 * g] > 0 && radii[2 * g + 1] > 0) order.push_back(g);
  std::sort(order.begin(), order.end(),
            [&](int64_t a, int64_t b) { return depths[a] < depths[b] || (depths[a] == depths[b] && a < b); });
  return order;
}

template <typename scalar_t>
std::vector<int64_t> depth_order(const int32_t* radii, const scalar_t* depths, int64_t N) {
  return compared_depth_order(radii, depths, N);
}

// float32: the same order by a stable LSD radix sort on the depths' bits (4 passes of 8 bits),
// a fifth of the comparison sort's time on ~40k Gaussians. A positive finite float's bits sort
// as its value; any other visible depth (none reach here from the projection, which culls
// before the near plane) takes the comparison sort.
template <>
std::vector<int64_t> depth_order<float>(const int32_t* radii, const float* depths, int64_t N) {
  std::vector<int64_t> order;
  std::vector<uint32_t> keys;
  order.reserve(N);
  keys.reserve(N);
  for (int64_t g = 0; g < N; ++g) {
    if (!(radii[2 * g] > 0 && radii[2 * g + 1] > 0)) continue;
    const float d = depths[g];
    if (!(d > 0.0f) || !std::isfinite(d)) return compared_depth_order(radii, depths, N);
    uint32_t bits;
    std::memcpy(&bits, &d, sizeof bits);
    order.push_back(g);
    keys.push_back(bits);
  }
  const size_t V = order.size();
  std::vector<int64_t> order_tmp(V);
  std::vector<uint32_t> keys_tmp(V);
  for (int shift = 0; shift < 32; shift += 8) {
    size_t count[257] = {0};
    for (size_t i = 0; i < V; ++i) ++count[((keys[i] >> shift) & 0xFF) + 1];
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (size_t i = 0; i < V; ++i) {
      const size_t pos = count[(keys[i] >> shift) & 0xFF]++;
      order_tmp[pos] = order[i];
      keys_tmp[pos] = keys[i];
    }
    order.swap(order_tmp);
    keys.swap(keys_tmp);
  }
  return order;
}

// Returns gauss_ids [M], tile_ids [M] (sorted by tile, front to back within a tile),
// tile_start [T], tile_count [T] for the visible Gaussians (radii [N, 2] int32 > 0).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> bin_tiles(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& radii,
    const at::Tensor& depths, int64_t width, int64_t height, int64_t tile_size) {
  TORCH_CHECK(means2d.device().is_cpu(), "eva_raster kernels run on the CPU");
  const int64_t N = means2d.size(0);
  TORCH_CHECK(means2d.sizes() == at::IntArrayRef({N, 2}) && conics.sizes() == at::IntArrayRef({N, 3}) &&
                  opacities.sizes() == at::IntArrayRef({N}) && radii.sizes() == at::IntArrayRef({N, 2}) &&
                  depths.sizes() == at::IntArrayRef({N}),
              "bin_tiles: means2d [N, 2], conics [N, 3], opacities [N], radii [N, 2], depths [N]");
  TORCH_CHECK(radii.scalar_type() == at::kInt, "radii must be int32");
  for (const auto* t : {&conics, &opacities, &depths})
    TORCH_CHECK(t->scalar_type() == means2d.scalar_type(), "all float inputs must share one dtype");
  const auto m = means2d.contiguous(), cn = conics.contiguous(), o = opacities.contiguous();
  const auto rd = radii.contiguous(), dp = depths.contiguous();
  const int64_t ts = tile_size, tiles_x = (width + ts - 1) / ts, tiles_y = (height + ts - 1) / ts;
  const int64_t n_tiles = tiles_x * tiles_y;
  const BinGeometry geo{ts, tiles_x, tiles_y, width, height};
  const int32_t* r = rd.data_ptr<int32_t>();
  std::vector<int64_t> ids, offs, kept;
  std::vector<int32_t> pair_tile;
  AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "eva_raster_bin_tiles", [&] {
    ids = depth_order(r, dp.data_ptr<scalar_t>(), N);
    const int64_t V = static_cast<int64_t>(ids.size());
    // Each Gaussian gets room for all its candidate tiles; one pass keeps those it reaches.
    offs.assign(V + 1, 0);
    kept.assign(V, 0);
    candidate_counts<scalar_t>(m.data_ptr<scalar_t>(), cn.data_ptr<scalar_t>(), o.data_ptr<scalar_t>(), r,
                               ids.data(), V, geo, offs.data() + 1);
    std::partial_sum(offs.begin(), offs.end(), offs.begin());
    pair_tile.resize(offs[V]);
    bin_pass<scalar_t>(m.data_ptr<scalar_t>(), cn.data_ptr<scalar_t>(), o.data_ptr<scalar_t>(), r, ids.data(), V,
                       geo, offs.data(), kept.data(), pair_tile.data());
  });
  // Stable counting sort by tile keeps the front-to-back order within each tile.
  const int64_t V = static_cast<int64_t>(ids.size());
  const auto lopt = rd.options().dtype(at::kLong);
  auto tile_count = at::zeros({n_tiles}, lopt);
  auto tile_start = at::empty({n_tiles}, lopt);
  int64_t* tc = tile_count.data_ptr<int64_t>();
  int64_t* tsd = tile_start.data_ptr<int64_t>();
  for (int64_t v = 0; v < V; ++v)
    for (int64_t i = offs[v]; i < offs[v] + kept[v]; ++i) ++tc[pair_tile[i]];
  int64_t M = 0;
  for (int64_t t = 0; t < n_tiles; ++t) {
    tsd[t] = M;
    M += tc[t];
  }
  auto gauss_ids = at::empty({M}, lopt);
  auto tile_ids = at::empty({M}, lopt);
  std::vector<int64_t> fill(tsd, tsd + n_tiles);
  int64_t* gi = gauss_ids.data_ptr<int64_t>();
  int64_t* ti = tile_ids.data_ptr<int64_t>();
  for (int64_t v = 0; v < V; ++v)
    for (int64_t i = offs[v]; i < offs[v] + kept[v]; ++i) {
      const int64_t t = pair_tile[i], pos = fill[t]++;
      gi[pos] = ids[v];
      ti[pos] = t;
    }
  return {gauss_ids, tile_ids, tile_start, tile_count};
}

// ------------------------------------------------------------------------------ projection
//
// EWA projection as in projection.py (gsplat "classic"), one Gaussian per iteration, in double
// whatever the tensors' dtype: the frustum-clamped Jacobian J, A = J W R S, cov2d = A A^T + eps2d I
// with its determinant via Cauchy-Binet, conic = cov2d^-1, the same culling, and the compensation
// sqrt(det(A A^T) / det(cov2d)) of gsplat's "antialiased" mode. The backward is the chain rule of
// exactly these steps.

struct CameraArgs {
  double Rw[9], tw[3], fx, fy, cx, cy, near, far, eps2d, ulo, uhi, vlo, vhi;
  int64_t width, height;

  CameraArgs(const at::Tensor& viewmat, const at::Tensor& K, int64_t w, int64_t h, double near_, double far_,
             double eps2d_)
      : near(near_), far(far_), eps2d(eps2d_), width(w), height(h) {
    TORCH_CHECK(viewmat.sizes() == at::IntArrayRef({4, 4}) && K.sizes() == at::IntArrayRef({3, 3}),
                "viewmat must be [4, 4] and K [3, 3]");
    const auto vm = viewmat.to(at::kDouble).contiguous(), k = K.to(at::kDouble).contiguous();
    const double* v = vm.data_ptr<double>();
    const double* kk = k.data_ptr<double>();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) Rw[3 * r + c] = v[4 * r + c];
      tw[r] = v[4 * r + 3];
    }
    fx = kk[0], fy = kk[4], cx = kk[2], cy = kk[5];
    // gsplat's frustum clamp of the point where J is evaluated: 1.3x the half field of view.
    const double margin = 0.3, tan_x = 0.5 * w / fx, tan_y = 0.5 * h / fy;
    ulo = -(cx / fx + margin * tan_x), uhi = (w - cx) / fx + margin * tan_x;
    vlo = -(cy / fy + margin * tan_y), vhi = (h - cy) / fy + margin * tan_y;
  }
};

// Unit quaternion (w, x, y, z) -> row-major rotation matrix.
inline void rotmat(const double q[4], double R[9]) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z), R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z), R[4] = 1 - 2 * (x * x + z * z), R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = 1 - 2 * (x * x + y * y);
}

// dL/dq of rotmat(q) given G = dL/dR (row-major).
inline void rotmat_grad(const double q[4], const double G[9], double dq[4]) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  dq[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
  dq[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]);
  dq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]);
  dq[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7]);
}

// Everything the forward computes for one Gaussian, kept for its backward.
struct ProjState {
  double p[3], zs, u, v, uc, vc, J[6], qn[4], qnorm, RwRq[9], M[9], A[6], m00, m01, m11, minor01, minor02,
      minor12, a, b, c, det, D, det_raw, comp;
  bool in_range, quat_ok, det_ok;
};

inline void project_one(const CameraArgs& cam, const double mean[3], const double quat[4], const double scale[3],
                        ProjState& st) {
  for (int r = 0; r < 3; ++r)
    st.p[r] = cam.Rw[3 * r] * mean[0] + cam.Rw[3 * r + 1] * mean[1] + cam.Rw[3 * r + 2] * mean[2] + cam.tw[r];
  st.in_range = st.p[2] >= cam.near && st.p[2] <= cam.far;
  st.zs = st.in_range ? st.p[2] : 1.0;  // a safe z keeps culled Gaussians' values finite
  st.u = st.p[0] / st.zs, st.v = st.p[1] / st.zs;
  st.uc = std::min(std::max(st.u, cam.ulo), cam.uhi);
  st.vc = std::min(std::max(st.v, cam.vlo), cam.vhi);
  st.J[0] = cam.fx / st.zs, st.J[1] = 0, st.J[2] = -cam.fx * st.uc / st.zs;
  st.J[3] = 0, st.J[4] = cam.fy / st.zs, st.J[5] = -cam.fy * st.vc / st.zs;
  st.qnorm = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  st.quat_ok = st.qnorm > 1e-12;  // the zero quaternion is the identity, with zero gradient
  for (int i = 0; i < 4; ++i) st.qn[i] = st.quat_ok ? quat[i] / st.qnorm : (i == 0 ? 1.0 : 0.0);
  double Rq[9];
  rotmat(st.qn, Rq);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j) {
      st.RwRq[3 * k + j] =
          cam.Rw[3 * k] * Rq[j] + cam.Rw[3 * k + 1] * Rq[3 + j] + cam.Rw[3 * k + 2] * Rq[6 + j];
      st.M[3 * k + j] = st.RwRq[3 * k + j] * scale[j];
    }
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      st.A[3 * i + j] = st.J[3 * i] * st.M[j] + st.J[3 * i + 1] * st.M[3 + j] + st.J[3 * i + 2] * st.M[6 + j];
  const double* A = st.A;
  st.m00 = A[0] * A[0] + A[1] * A[1] + A[2] * A[2];
  st.m01 = A[0] * A[3] + A[1] * A[4] + A[2] * A[5];
  st.m11 = A[3] * A[3] + A[4] * A[4] + A[5] * A[5];
  st.minor01 = A[0] * A[4] - A[1] * A[3];
  st.minor02 = A[0] * A[5] - A[2] * A[3];
  st.minor12 = A[1] * A[5] - A[2] * A[4];
  const double e = cam.eps2d;
  st.a = st.m00 + e, st.b = st.m01, st.c = st.m11 + e;
  // Non-negative by construction, unlike a c - b^2, which cancels in float32 for needles.
  st.det = st.minor01 * st.minor01 + st.minor02 * st.minor02 + st.minor12 * st.minor12 + e * (st.m00 + st.m11) +
           e * e;
  st.det_ok = st.det > 0;
  st.D = st.det_ok ? st.det : 1.0;
  st.det_raw = st.minor01 * st.minor01 + st.minor02 * st.minor02 + st.minor12 * st.minor12;
  st.comp = std::sqrt(std::max(st.det_raw / st.D, 0.0));
}

template <typename scalar_t>
void project_forward_kernel(const CameraArgs& cam, const scalar_t* means, const scalar_t* quats,
                            const scalar_t* scales, int64_t N, scalar_t* means2d, scalar_t* conics, scalar_t* depths,
                            scalar_t* compensations, int32_t* radii) {
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    const double mean[3] = {double(means[3 * g]), double(means[3 * g + 1]), double(means[3 * g + 2])};
    const double quat[4] = {double(quats[4 * g]), double(quats[4 * g + 1]), double(quats[4 * g + 2]),
                            double(quats[4 * g + 3])};
    const double scale[3] = {double(scales[3 * g]), double(scales[3 * g + 1]), double(scales[3 * g + 2])};
    ProjState st;
    project_one(cam, mean, quat, scale, st);
    const scalar_t mx = static_cast<scalar_t>(cam.fx * st.u + cam.cx);
    const scalar_t my = static_cast<scalar_t>(cam.fy * st.v + cam.cy);
    const scalar_t ca = static_cast<scalar_t>(st.c / st.D), cb = static_cast<scalar_t>(-st.b / st.D),
                   cc = static_cast<scalar_t>(st.a / st.D);
    means2d[2 * g] = mx, means2d[2 * g + 1] = my;
    conics[3 * g] = ca, conics[3 * g + 1] = cb, conics[3 * g + 2] = cc;
    depths[g] = static_cast<scalar_t>(st.p[2]);
    compensations[g] = static_cast<scalar_t>(st.comp);
    // Radii in the tensors' dtype, as the torch projection computes them.
    const scalar_t sig = static_cast<scalar_t>(3.33);
    const scalar_t rx = std::ceil(sig * std::sqrt(std::max(static_cast<scalar_t>(st.a), scalar_t(0))));
    const scalar_t ry = std::ceil(sig * std::sqrt(std::max(static_cast<scalar_t>(st.c), scalar_t(0))));
    const bool on_image = (mx + rx > 0) && (mx - rx < cam.width) && (my + ry > 0) && (my - ry < cam.height);
    const bool finite = std::isfinite(mx) && std::isfinite(my) && std::isfinite(ca) && std::isfinite(cb) &&
                        std::isfinite(cc);
    const bool keep = st.in_range && st.det_ok && rx > 0 && ry > 0 && on_image && finite;
    const scalar_t cap = static_cast<scalar_t>(1 << 30);  // a Gaussian at the near plane can be huge
    radii[2 * g] = keep ? static_cast<int32_t>(std::min(rx, cap)) : 0;
    radii[2 * g + 1] = keep ? static_cast<int32_t>(std::min(ry, cap)) : 0;
  }
}

template <typename scalar_t>
void project_backward_kernel(const CameraArgs& cam, const scalar_t* means, const scalar_t* quats,
                             const scalar_t* scales, int64_t N, const scalar_t* g_means2d, const scalar_t* g_conics,
                             const scalar_t* g_depths, const scalar_t* g_comps, scalar_t* g_means, scalar_t* g_quats,
                             scalar_t* g_scales) {
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    const double mean[3] = {double(means[3 * g]), double(means[3 * g + 1]), double(means[3 * g + 2])};
    const double quat[4] = {double(quats[4 * g]), double(quats[4 * g + 1]), double(quats[4 * g + 2]),
                            double(quats[4 * g + 3])};
    const double scale[3] = {double(scales[3 * g]), double(scales[3 * g + 1]), double(scales[3 * g + 2])};
    ProjState st;
    project_one(cam, mean, quat, scale, st);
    const double gm0 = g_means2d[2 * g], gm1 = g_means2d[2 * g + 1];
    const double gca = g_conics[3 * g], gcb = g_conics[3 * g + 1], gcc = g_conics[3 * g + 2];
    // conic = (c, -b, a) / D
    const double D = st.D;
    const double da = gcc / D, db = -gcb / D, dc = gca / D;
    double dD = st.det_ok ? -(gca * st.c - gcb * st.b + gcc * st.a) / (D * D) : 0.0;
    // comp = sqrt(det_raw / D): d comp = (d det_raw - comp^2 d D) / (2 comp D) (gsplat's 1e-6 keeps
    // a degenerate Gaussian's gradient finite).
    const double gcomp = g_comps[g], half = st.det_ok ? 0.5 * gcomp / ((st.comp + 1e-6) * D) : 0.0;
    const double ddet_raw = half;
    dD -= half * st.comp * st.comp;
    const double e = cam.eps2d;
    const double dm00 = da + e * dD, dm11 = dc + e * dD, dm01 = db;
    const double g01 = 2 * st.minor01 * (dD + ddet_raw), g02 = 2 * st.minor02 * (dD + ddet_raw),
                 g12 = 2 * st.minor12 * (dD + ddet_raw);
    const double* A = st.A;
    double dA[6];
    for (int j = 0; j < 3; ++j) {
      dA[j] = 2 * A[j] * dm00 + A[3 + j] * dm01;
      dA[3 + j] = 2 * A[3 + j] * dm11 + A[j] * dm01;
    }
    dA[0] += A[4] * g01, dA[4] += A[0] * g01, dA[1] -= A[3] * g01, dA[3] -= A[1] * g01;  // minor01
    dA[0] += A[5] * g02, dA[5] += A[0] * g02, dA[2] -= A[3] * g02, dA[3] -= A[2] * g02;  // minor02
    dA[1] += A[5] * g12, dA[5] += A[1] * g12, dA[2] -= A[4] * g12, dA[4] -= A[2] * g12;  // minor12
    // A = J M
    double dJ[6], dM[9];
    for (int i = 0; i < 2; ++i)
      for (int k = 0; k < 3; ++k)
        dJ[3 * i + k] = dA[3 * i] * st.M[3 * k] + dA[3 * i + 1] * st.M[3 * k + 1] + dA[3 * i + 2] * st.M[3 * k + 2];
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 3; ++j) dM[3 * k + j] = st.J[k] * dA[j] + st.J[3 + k] * dA[3 + j];
    // M = (Rw Rq) diag(scale)
    double ds[3] = {0, 0, 0}, dRq[9];
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 3; ++j) ds[j] += dM[3 * k + j] * st.RwRq[3 * k + j];
    for (int l = 0; l < 3; ++l)
      for (int j = 0; j < 3; ++j)
        dRq[3 * l + j] =
            (cam.Rw[l] * dM[j] + cam.Rw[3 + l] * dM[3 + j] + cam.Rw[6 + l] * dM[6 + j]) * scale[j];
    double dq[4] = {0, 0, 0, 0};
    if (st.quat_ok) {
      double dqn[4];
      rotmat_grad(st.qn, dRq, dqn);
      const double dot = st.qn[0] * dqn[0] + st.qn[1] * dqn[1] + st.qn[2] * dqn[2] + st.qn[3] * dqn[3];
      for (int i = 0; i < 4; ++i) dq[i] = (dqn[i] - st.qn[i] * dot) / st.qnorm;
    }
    // J = [[fx / zs, 0, -fx uc / zs], [0, fy / zs, -fy vc / zs]], uc / vc the clamped u / v
    const double zs = st.zs, z2 = zs * zs;
    double dzs = -cam.fx / z2 * dJ[0] + cam.fx * st.uc / z2 * dJ[2] - cam.fy / z2 * dJ[4] + cam.fy * st.vc / z2 * dJ[5];
    const double duc = -cam.fx / zs * dJ[2], dvc = -cam.fy / zs * dJ[5];
    const double du = cam.fx * gm0 + ((st.u > cam.ulo && st.u < cam.uhi) ? duc : 0.0);
    const double dv = cam.fy * gm1 + ((st.v > cam.vlo && st.v < cam.vhi) ? dvc : 0.0);
    dzs -= (du * st.u + dv * st.v) / zs;  // u = x / zs, v = y / zs
    const double dp[3] = {du / zs, dv / zs, double(g_depths[g]) + (st.in_range ? dzs : 0.0)};
    for (int c = 0; c < 3; ++c)
      g_means[3 * g + c] = static_cast<scalar_t>(cam.Rw[c] * dp[0] + cam.Rw[3 + c] * dp[1] + cam.Rw[6 + c] * dp[2]);
    for (int i = 0; i < 4; ++i) g_quats[4 * g + i] = static_cast<scalar_t>(dq[i]);
    for (int j = 0; j < 3; ++j) g_scales[3 * g + j] = static_cast<scalar_t>(ds[j]);
  }
}

void check_gaussians(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales) {
  TORCH_CHECK(means.device().is_cpu(), "eva_raster kernels run on the CPU");
  const int64_t n = means.size(0);
  TORCH_CHECK(means.sizes() == at::IntArrayRef({n, 3}) && quats.sizes() == at::IntArrayRef({n, 4}) &&
                  scales.sizes() == at::IntArrayRef({n, 3}),
              "means [N, 3], quats [N, 4], scales [N, 3]");
  TORCH_CHECK(quats.scalar_type() == means.scalar_type() && scales.scalar_type() == means.scalar_type(),
              "means, quats and scales must share one dtype");
}

// Returns means2d [N, 2], conics [N, 3], depths [N], compensations [N], radii [N, 2] (int32, 0 = culled).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_forward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& viewmat,
    const at::Tensor& K, int64_t width, int64_t height, double near_plane, double far_plane, double eps2d) {
  check_gaussians(means, quats, scales);
  const CameraArgs cam(viewmat, K, width, height, near_plane, far_plane, eps2d);
  const auto m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous();
  const int64_t N = m.size(0);
  auto means2d = at::empty({N, 2}, m.options());
  auto conics = at::empty({N, 3}, m.options());
  auto depths = at::empty({N}, m.options());
  auto compensations = at::empty({N}, m.options());
  auto radii = at::empty({N, 2}, m.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "eva_raster_project_forward", [&] {
    project_forward_kernel<scalar_t>(cam, m.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), s.data_ptr<scalar_t>(), N,
                                     means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                     depths.data_ptr<scalar_t>(), compensations.data_ptr<scalar_t>(),
                                     radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, compensations, radii};
}

// Returns dL/dmeans [N, 3], dL/dquats [N, 4], dL/dscales [N, 3].
std::tuple<at::Tensor, at::Tensor, at::Tensor> project_backward(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& viewmat,
    const at::Tensor& K, int64_t width, int64_t height, double near_plane, double far_plane, double eps2d,
    const at::Tensor& grad_means2d, const at::Tensor& grad_conics, const at::Tensor& grad_depths,
    const at::Tensor& grad_compensations) {
  check_gaussians(means, quats, scales);
  const CameraArgs cam(viewmat, K, width, height, near_plane, far_plane, eps2d);
  const auto m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous();
  const int64_t N = m.size(0);
  TORCH_CHECK(grad_means2d.numel() == 2 * N && grad_conics.numel() == 3 * N && grad_depths.numel() == N &&
                  grad_compensations.numel() == N,
              "gradients must be [N, 2], [N, 3], [N] and [N]");
  const auto dt = m.scalar_type();
  const auto gm = grad_means2d.contiguous().to(dt), gc = grad_conics.contiguous().to(dt);
  const auto gd = grad_depths.contiguous().to(dt), gk = grad_compensations.contiguous().to(dt);
  auto g_means = at::empty({N, 3}, m.options());
  auto g_quats = at::empty({N, 4}, m.options());
  auto g_scales = at::empty({N, 3}, m.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "eva_raster_project_backward", [&] {
    project_backward_kernel<scalar_t>(cam, m.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), s.data_ptr<scalar_t>(),
                                      N, gm.data_ptr<scalar_t>(), gc.data_ptr<scalar_t>(), gd.data_ptr<scalar_t>(),
                                      gk.data_ptr<scalar_t>(), g_means.data_ptr<scalar_t>(), g_quats.data_ptr<scalar_t>(),
                                      g_scales.data_ptr<scalar_t>());
  });
  return {g_means, g_quats, g_scales};
}

// ------------------------------------------------------------------------------ SH colours
//
// eval_sh of sh.py: rgb = max(sum_k Y_k(u) c_k + 0.5, 0) with u = dir / |dir| (a zero direction
// stays zero), one Gaussian per iteration in double. Y_k and their derivatives are the
// polynomials in (x, y, z) = u that sh.py differentiates with autograd.

constexpr double kC0 = 0.28209479177387814, kC1 = 0.4886025119029199;
constexpr double kC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                           0.5462742152960396};
constexpr double kC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                           -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

// Y [16] (the first (degree + 1)^2 used) and, if dY is given, dY/d(x, y, z) [16][3].
inline void sh_basis_one(int degree, double x, double y, double z, double* Y, double (*dY)[3]) {
  Y[0] = kC0;
  if (dY) dY[0][0] = dY[0][1] = dY[0][2] = 0;
  if (degree >= 1) {
    Y[1] = -kC1 * y, Y[2] = kC1 * z, Y[3] = -kC1 * x;
    if (dY) {
      dY[1][0] = 0, dY[1][1] = -kC1, dY[1][2] = 0;
      dY[2][0] = 0, dY[2][1] = 0, dY[2][2] = kC1;
      dY[3][0] = -kC1, dY[3][1] = 0, dY[3][2] = 0;
    }
  }
  const double xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  if (degree >= 2) {
    Y[4] = kC2[0] * xy, Y[5] = kC2[1] * yz, Y[6] = kC2[2] * (2 * zz - xx - yy), Y[7] = kC2[3] * xz,
    Y[8] = kC2[4] * (xx - yy);
    if (dY) {
      dY[4][0] = kC2[0] * y, dY[4][1] = kC2[0] * x, dY[4][2] = 0;
      dY[5][0] = 0, dY[5][1] = kC2[1] * z, dY[5][2] = kC2[1] * y;
      dY[6][0] = -2 * kC2[2] * x, dY[6][1] = -2 * kC2[2] * y, dY[6][2] = 4 * kC2[2] * z;
      dY[7][0] = kC2[3] * z, dY[7][1] = 0, dY[7][2] = kC2[3] * x;
      dY[8][0] = 2 * kC2[4] * x, dY[8][1] = -2 * kC2[4] * y, dY[8][2] = 0;
    }
  }
  if (degree >= 3) {
    Y[9] = kC3[0] * y * (3 * xx - yy);
    Y[10] = kC3[1] * xy * z;
    Y[11] = kC3[2] * y * (4 * zz - xx - yy);
    Y[12] = kC3[3] * z * (2 * zz - 3 * xx - 3 * yy);
    Y[13] = kC3[4] * x * (4 * zz - xx - yy);
    Y[14] = kC3[5] * z * (xx - yy);
    Y[15] = kC3[6] * x * (xx - 3 * yy);
    if (dY) {
      dY[9][0] = 6 * kC3[0] * xy, dY[9][1] = kC3[0] * (3 * xx - 3 * yy), dY[9][2] = 0;
      dY[10][0] = kC3[1] * yz, dY[10][1] = kC3[1] * xz, dY[10][2] = kC3[1] * xy;
      dY[11][0] = -2 * kC3[2] * xy, dY[11][1] = kC3[2] * (4 * zz - xx - 3 * yy), dY[11][2] = 8 * kC3[2] * yz;
      dY[12][0] = -6 * kC3[3] * xz, dY[12][1] = -6 * kC3[3] * yz, dY[12][2] = kC3[3] * (6 * zz - 3 * xx - 3 * yy);
      dY[13][0] = kC3[4] * (4 * zz - 3 * xx - yy), dY[13][1] = -2 * kC3[4] * xy, dY[13][2] = 8 * kC3[4] * xz;
      dY[14][0] = 2 * kC3[5] * xz, dY[14][1] = -2 * kC3[5] * yz, dY[14][2] = kC3[5] * (xx - yy);
      dY[15][0] = kC3[6] * (3 * xx - 3 * yy), dY[15][1] = -6 * kC3[6] * xy, dY[15][2] = 0;
    }
  }
}

template <typename scalar_t>
inline void unit_dir(const scalar_t* d, double u[3], double& n) {
  const double x = d[0], y = d[1], z = d[2];
  n = std::sqrt(x * x + y * y + z * z);
  const double inv = n > 0 ? 1.0 / n : 1.0;
  u[0] = x * inv, u[1] = y * inv, u[2] = z * inv;
}

template <typename scalar_t>
void sh_forward_kernel(int degree, const scalar_t* coeffs, int64_t K, const scalar_t* dirs, int64_t N,
                       scalar_t* rgb) {
  const int B = (degree + 1) * (degree + 1);
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    double u[3], n, Y[16];
    unit_dir(dirs + 3 * g, u, n);
    sh_basis_one(degree, u[0], u[1], u[2], Y, nullptr);
    const scalar_t* c = coeffs + g * K * 3;
    for (int ch = 0; ch < 3; ++ch) {
      double v = 0.5;
      for (int k = 0; k < B; ++k) v += Y[k] * c[3 * k + ch];
      rgb[3 * g + ch] = static_cast<scalar_t>(std::max(v, 0.0));
    }
  }
}

template <typename scalar_t>
void sh_backward_kernel(int degree, const scalar_t* coeffs, int64_t K, const scalar_t* dirs, int64_t N,
                        const scalar_t* g_rgb, scalar_t* g_coeffs, scalar_t* g_dirs) {
  const int B = (degree + 1) * (degree + 1);
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    double u[3], n, Y[16], dY[16][3];
    unit_dir(dirs + 3 * g, u, n);
    sh_basis_one(degree, u[0], u[1], u[2], Y, dY);
    const scalar_t* c = coeffs + g * K * 3;
    scalar_t* gc = g_coeffs + g * K * 3;
    double gv[3];
    for (int ch = 0; ch < 3; ++ch) {
      double v = 0.5;
      for (int k = 0; k < B; ++k) v += Y[k] * c[3 * k + ch];
      gv[ch] = v >= 0.0 ? double(g_rgb[3 * g + ch]) : 0.0;  // clamp_min passes ties, as torch
    }
    double gu[3] = {0, 0, 0};
    for (int k = 0; k < K; ++k)
      for (int ch = 0; ch < 3; ++ch) {
        gc[3 * k + ch] = static_cast<scalar_t>(k < B ? Y[k] * gv[ch] : 0.0);
        if (k < B) {
          const double w = c[3 * k + ch] * gv[ch];
          gu[0] += w * dY[k][0], gu[1] += w * dY[k][1], gu[2] += w * dY[k][2];
        }
      }
    // u = d / |d| (d / 1 for a zero direction)
    if (n > 0) {
      const double dot = u[0] * gu[0] + u[1] * gu[1] + u[2] * gu[2];
      for (int r = 0; r < 3; ++r) g_dirs[3 * g + r] = static_cast<scalar_t>((gu[r] - u[r] * dot) / n);
    } else {
      for (int r = 0; r < 3; ++r) g_dirs[3 * g + r] = static_cast<scalar_t>(gu[r]);
    }
  }
}

void check_sh(int64_t degree, const at::Tensor& coeffs, const at::Tensor& dirs) {
  TORCH_CHECK(coeffs.device().is_cpu(), "eva_raster kernels run on the CPU");
  TORCH_CHECK(degree >= 0 && degree <= 3, "SH degree must be in 0..3");
  const int64_t n = dirs.size(0);
  TORCH_CHECK(dirs.dim() == 2 && dirs.size(1) == 3 && coeffs.dim() == 3 && coeffs.size(0) == n &&
                  coeffs.size(2) == 3 && coeffs.size(1) >= (degree + 1) * (degree + 1),
              "coeffs [N, K >= (degree + 1)^2, 3] and dirs [N, 3]");
  TORCH_CHECK(coeffs.scalar_type() == dirs.scalar_type(), "coeffs and dirs must share one dtype");
}

// Returns rgb [N, 3].
at::Tensor sh_forward(int64_t degree, const at::Tensor& coeffs, const at::Tensor& dirs) {
  check_sh(degree, coeffs, dirs);
  const auto c = coeffs.contiguous(), d = dirs.contiguous();
  const int64_t N = d.size(0), K = c.size(1);
  auto rgb = at::empty({N, 3}, d.options());
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "eva_raster_sh_forward", [&] {
    sh_forward_kernel<scalar_t>(static_cast<int>(degree), c.data_ptr<scalar_t>(), K, d.data_ptr<scalar_t>(), N,
                                rgb.data_ptr<scalar_t>());
  });
  return rgb;
}

// Returns dL/dcoeffs [N, K, 3] (0 beyond the degree's coefficients) and dL/ddirs [N, 3].
std::tuple<at::Tensor, at::Tensor> sh_backward(int64_t degree, const at::Tensor& coeffs, const at::Tensor& dirs,
                                               const at::Tensor& grad_rgb) {
  check_sh(degree, coeffs, dirs);
  const auto c = coeffs.contiguous(), d = dirs.contiguous();
  const auto g = grad_rgb.contiguous().to(d.scalar_type());
  const int64_t N = d.size(0), K = c.size(1);
  TORCH_CHECK(g.numel() == 3 * N, "grad_rgb must be [N, 3]");
  auto g_coeffs = at::empty({N, K, 3}, d.options());
  auto g_dirs = at::empty({N, 3}, d.options());
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "eva_raster_sh_backward", [&] {
    sh_backward_kernel<scalar_t>(static_cast<int>(degree), c.data_ptr<scalar_t>(), K, d.data_ptr<scalar_t>(), N,
                                 g.data_ptr<scalar_t>(), g_coeffs.data_ptr<scalar_t>(), g_dirs.data_ptr<scalar_t>());
  });
  return {g_coeffs, g_dirs};
}

}  // namespace

TORCH_LIBRARY(eva_raster, m) {
  m.def("composite_image_forward", &composite_image_forward);
  m.def("composite_image_backward", &composite_image_backward);
  m.def("bin_tiles", &bin_tiles);
  m.def("project_forward", &project_forward);
  m.def("project_backward", &project_backward);
  m.def("sh_forward", &sh_forward);
  m.def("sh_backward", &sh_backward);
}
