// Compiled CPU kernel of eva_engine.avatar.skinning.skin_gaussians: the per-Gaussian part of
// linear blend skinning, forward and hand-written backward, one Gaussian per iteration, in double
// whatever the tensors' dtype. The blend A = sum_k w_k T_k itself is a matrix product, which
// skinning.py leaves to torch. Built by eva_engine/native.py; the torch version in skinning.py
// follows the same steps and stays the fallback:
//
//   posed = A[:, :3] p + A[:, 3]     (A: the blended 3x4 transform, row-major)
//   R = Gram-Schmidt(A[:, :3])       (columns r1, r2 from the first two, r3 = r1 x r2; eps as given)
//   q(R): Markley's variant of Shepperd's method exactly as roma.rotmat_to_unitquat computes it
//   posed quat = q(R) (x) q_c        (Hamilton product, w x y z)
//
// Nothing sums over Gaussians, so the results do not depend on the thread count.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

namespace {

int num_threads() { return std::max(1, at::get_num_threads()); }

inline double dot3(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

inline void cross3(const double a[3], const double b[3], double c[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

// Everything the forward computes for one Gaussian, kept for its backward.
struct SkinState {
  double A[12];           // blended transform, row-major 3x4
  double a1[3], a2[3];    // the first two columns of A[:, :3]
  double n1, r1[3], s;    // |a1|, r1, s = r1 . a2
  double a2p[3], n2, r2[3], r3[3];
  double x[4], xn;        // the chosen Shepperd row (x y z w) and its norm
  int branch;
  double qr[4];           // q(R), w x y z
};

template <typename scalar_t>
inline void skin_one(const scalar_t* blended, double eps, SkinState& st) {
  double* A = st.A;
  for (int e = 0; e < 12; ++e) A[e] = static_cast<double>(blended[e]);
  for (int r = 0; r < 3; ++r) st.a1[r] = A[4 * r], st.a2[r] = A[4 * r + 1];
  st.n1 = std::sqrt(dot3(st.a1, st.a1));
  for (int r = 0; r < 3; ++r) st.r1[r] = st.a1[r] / (st.n1 + eps);
  st.s = dot3(st.r1, st.a2);
  for (int r = 0; r < 3; ++r) st.a2p[r] = st.a2[r] - st.s * st.r1[r];
  st.n2 = std::sqrt(dot3(st.a2p, st.a2p));
  for (int r = 0; r < 3; ++r) st.r2[r] = st.a2p[r] / (st.n2 + eps);
  cross3(st.r1, st.r2, st.r3);
  // roma's notation: the attitude matrix a = R^T, so a_ij = R[j][i] with R's columns r1 r2 r3.
  const double a11 = st.r1[0], a12 = st.r1[1], a13 = st.r1[2];
  const double a21 = st.r2[0], a22 = st.r2[1], a23 = st.r2[2];
  const double a31 = st.r3[0], a32 = st.r3[1], a33 = st.r3[2];
  const double d[4] = {1 + a11 - a22 - a33, 1 + a22 - a33 - a11, 1 + a33 - a11 - a22, 1 + a11 + a22 + a33};
  int i = 0;
  for (int c = 1; c < 4; ++c)
    if (d[c] > d[i]) i = c;  // the first maximum, as torch.argmax
  st.branch = i;
  double* x = st.x;
  if (i == 0) x[0] = d[0], x[1] = a12 + a21, x[2] = a13 + a31, x[3] = a23 - a32;
  if (i == 1) x[0] = a21 + a12, x[1] = d[1], x[2] = a23 + a32, x[3] = a31 - a13;
  if (i == 2) x[0] = a31 + a13, x[1] = a32 + a23, x[2] = d[2], x[3] = a12 - a21;
  if (i == 3) x[0] = a23 - a32, x[1] = a31 - a13, x[2] = a12 - a21, x[3] = d[3];
  st.xn = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3]);
  st.qr[0] = x[3] / st.xn, st.qr[1] = x[0] / st.xn, st.qr[2] = x[1] / st.xn, st.qr[3] = x[2] / st.xn;
}

inline void hamilton(const double a[4], const double b[4], double out[4]) {
  out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
  out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
  out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
  out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

template <typename scalar_t>
void skin_forward_kernel(const scalar_t* means, const scalar_t* quats, const scalar_t* blended, int64_t N,
                         double eps, scalar_t* posed, scalar_t* posed_quats, scalar_t* rots) {
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    SkinState st;
    skin_one(blended + 12 * g, eps, st);
    const double p[3] = {double(means[3 * g]), double(means[3 * g + 1]), double(means[3 * g + 2])};
    for (int r = 0; r < 3; ++r)
      posed[3 * g + r] =
          static_cast<scalar_t>(st.A[4 * r] * p[0] + st.A[4 * r + 1] * p[1] + st.A[4 * r + 2] * p[2] + st.A[4 * r + 3]);
    const double qc[4] = {double(quats[4 * g]), double(quats[4 * g + 1]), double(quats[4 * g + 2]),
                          double(quats[4 * g + 3])};
    double q[4];
    hamilton(st.qr, qc, q);
    for (int c = 0; c < 4; ++c) posed_quats[4 * g + c] = static_cast<scalar_t>(q[c]);
    for (int r = 0; r < 3; ++r) {
      rots[9 * g + 3 * r] = static_cast<scalar_t>(st.r1[r]);
      rots[9 * g + 3 * r + 1] = static_cast<scalar_t>(st.r2[r]);
      rots[9 * g + 3 * r + 2] = static_cast<scalar_t>(st.r3[r]);
    }
  }
}

// d/da (a attitude-matrix entries, a[i][j] = a_{i+1, j+1}) of the chosen Shepperd row, given dx.
inline void shepperd_grad(int branch, const double dx[4], double da[3][3]) {
  switch (branch) {
    case 0:
      da[0][0] += dx[0], da[1][1] -= dx[0], da[2][2] -= dx[0];
      da[0][1] += dx[1], da[1][0] += dx[1], da[0][2] += dx[2], da[2][0] += dx[2];
      da[1][2] += dx[3], da[2][1] -= dx[3];
      break;
    case 1:
      da[1][0] += dx[0], da[0][1] += dx[0];
      da[1][1] += dx[1], da[2][2] -= dx[1], da[0][0] -= dx[1];
      da[1][2] += dx[2], da[2][1] += dx[2], da[2][0] += dx[3], da[0][2] -= dx[3];
      break;
    case 2:
      da[2][0] += dx[0], da[0][2] += dx[0], da[2][1] += dx[1], da[1][2] += dx[1];
      da[2][2] += dx[2], da[0][0] -= dx[2], da[1][1] -= dx[2];
      da[0][1] += dx[3], da[1][0] -= dx[3];
      break;
    default:
      da[1][2] += dx[0], da[2][1] -= dx[0], da[2][0] += dx[1], da[0][2] -= dx[1];
      da[0][1] += dx[2], da[1][0] -= dx[2];
      da[0][0] += dx[3], da[1][1] += dx[3], da[2][2] += dx[3];
  }
}

// d/dv of v / (|v| + eps) given the output gradient g; |v| = n (the norm's gradient at 0 is 0,
// as torch's).
inline void normalized_grad(const double v[3], double n, double eps, const double g[3], double dv[3]) {
  const double inv = 1.0 / (n + eps);
  const double k = n > 0 ? dot3(v, g) * inv * inv / n : 0.0;
  for (int r = 0; r < 3; ++r) dv[r] = g[r] * inv - v[r] * k;
}

template <typename scalar_t>
void skin_backward_kernel(const scalar_t* means, const scalar_t* quats, const scalar_t* blended, int64_t N,
                          double eps, const scalar_t* g_posed, const scalar_t* g_quats, const scalar_t* g_rots,
                          scalar_t* d_means, scalar_t* d_quats, scalar_t* d_blended) {
#pragma omp parallel for schedule(static) num_threads(num_threads())
  for (int64_t g = 0; g < N; ++g) {
    SkinState st;
    skin_one(blended + 12 * g, eps, st);
    const double p[3] = {double(means[3 * g]), double(means[3 * g + 1]), double(means[3 * g + 2])};
    const double qc[4] = {double(quats[4 * g]), double(quats[4 * g + 1]), double(quats[4 * g + 2]),
                          double(quats[4 * g + 3])};
    const double gq[4] = {double(g_quats[4 * g]), double(g_quats[4 * g + 1]), double(g_quats[4 * g + 2]),
                          double(g_quats[4 * g + 3])};
    const double gp[3] = {double(g_posed[3 * g]), double(g_posed[3 * g + 1]), double(g_posed[3 * g + 2])};
    // posed quat = qr (x) qc
    const double* q1 = st.qr;
    const double dq1[4] = {gq[0] * qc[0] + gq[1] * qc[1] + gq[2] * qc[2] + gq[3] * qc[3],
                           -gq[0] * qc[1] + gq[1] * qc[0] - gq[2] * qc[3] + gq[3] * qc[2],
                           -gq[0] * qc[2] + gq[1] * qc[3] + gq[2] * qc[0] - gq[3] * qc[1],
                           -gq[0] * qc[3] - gq[1] * qc[2] + gq[2] * qc[1] + gq[3] * qc[0]};
    d_quats[4 * g] = static_cast<scalar_t>(gq[0] * q1[0] + gq[1] * q1[1] + gq[2] * q1[2] + gq[3] * q1[3]);
    d_quats[4 * g + 1] = static_cast<scalar_t>(-gq[0] * q1[1] + gq[1] * q1[0] + gq[2] * q1[3] - gq[3] * q1[2]);
    d_quats[4 * g + 2] = static_cast<scalar_t>(-gq[0] * q1[2] - gq[1] * q1[3] + gq[2] * q1[0] + gq[3] * q1[1]);
    d_quats[4 * g + 3] = static_cast<scalar_t>(-gq[0] * q1[3] + gq[1] * q1[2] - gq[2] * q1[1] + gq[3] * q1[0]);
    // qr (w x y z) = x_i (x y z w) / |x_i|
    const double dq[4] = {dq1[1], dq1[2], dq1[3], dq1[0]};  // x y z w
    const double* x = st.x;
    const double qn[4] = {x[0] / st.xn, x[1] / st.xn, x[2] / st.xn, x[3] / st.xn};
    const double proj = qn[0] * dq[0] + qn[1] * dq[1] + qn[2] * dq[2] + qn[3] * dq[3];
    double dx[4];
    for (int c = 0; c < 4; ++c) dx[c] = (dq[c] - qn[c] * proj) / st.xn;
    double da[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
    shepperd_grad(st.branch, dx, da);
    // R[r][c] = a[c][r]: column c of R is row c of a; plus the rotations' own gradient.
    double dr1[3], dr2[3], dr3[3];
    for (int r = 0; r < 3; ++r) {
      dr1[r] = da[0][r] + double(g_rots[9 * g + 3 * r]);
      dr2[r] = da[1][r] + double(g_rots[9 * g + 3 * r + 1]);
      dr3[r] = da[2][r] + double(g_rots[9 * g + 3 * r + 2]);
    }
    // r3 = r1 x r2
    double t1[3], t2[3];
    cross3(st.r2, dr3, t1);
    cross3(dr3, st.r1, t2);
    for (int r = 0; r < 3; ++r) dr1[r] += t1[r], dr2[r] += t2[r];
    // r2 = a2p / (|a2p| + eps), a2p = a2 - (r1 . a2) r1
    double da2p[3];
    normalized_grad(st.a2p, st.n2, eps, dr2, da2p);
    const double r1u = dot3(st.r1, da2p);
    double da2[3];
    for (int r = 0; r < 3; ++r) {
      da2[r] = da2p[r] - st.r1[r] * r1u;
      dr1[r] -= r1u * st.a2[r] + st.s * da2p[r];
    }
    // r1 = a1 / (|a1| + eps)
    double da1[3];
    normalized_grad(st.a1, st.n1, eps, dr1, da1);
    // posed = A[:, :3] p + A[:, 3]
    double dA[12];
    for (int r = 0; r < 3; ++r) {
      dA[4 * r] = da1[r] + gp[r] * p[0];
      dA[4 * r + 1] = da2[r] + gp[r] * p[1];
      dA[4 * r + 2] = gp[r] * p[2];
      dA[4 * r + 3] = gp[r];
    }
    for (int c = 0; c < 3; ++c)
      d_means[3 * g + c] =
          static_cast<scalar_t>(st.A[c] * gp[0] + st.A[4 + c] * gp[1] + st.A[8 + c] * gp[2]);
    for (int e = 0; e < 12; ++e) d_blended[12 * g + e] = static_cast<scalar_t>(dA[e]);
  }
}

void check_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& blended) {
  TORCH_CHECK(means.device().is_cpu(), "eva_skinning kernels run on the CPU");
  const int64_t n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && quats.sizes() == at::IntArrayRef({n, 4}) &&
                  blended.sizes() == at::IntArrayRef({n, 12}),
              "means [N, 3], quats [N, 4], blended transforms [N, 12]");
  TORCH_CHECK(quats.scalar_type() == means.scalar_type() && blended.scalar_type() == means.scalar_type(),
              "means, quats and blended transforms must share one dtype");
}

// Returns posed means [N, 3], posed quats [N, 4] and rotations [N, 3, 3].
std::tuple<at::Tensor, at::Tensor, at::Tensor> skin_forward(const at::Tensor& means, const at::Tensor& quats,
                                                            const at::Tensor& blended, double eps) {
  check_inputs(means, quats, blended);
  const auto m = means.contiguous(), q = quats.contiguous(), a = blended.contiguous();
  const int64_t N = m.size(0);
  auto posed = at::empty({N, 3}, m.options());
  auto posed_quats = at::empty({N, 4}, m.options());
  auto rots = at::empty({N, 3, 3}, m.options());
  AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "eva_skinning_forward", [&] {
    skin_forward_kernel<scalar_t>(m.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(), N, eps,
                                  posed.data_ptr<scalar_t>(), posed_quats.data_ptr<scalar_t>(),
                                  rots.data_ptr<scalar_t>());
  });
  return {posed, posed_quats, rots};
}

// Returns the gradients of means [N, 3], quats [N, 4] and the blended transforms [N, 12].
std::tuple<at::Tensor, at::Tensor, at::Tensor> skin_backward(const at::Tensor& means, const at::Tensor& quats,
                                                             const at::Tensor& blended, double eps,
                                                             const at::Tensor& g_posed, const at::Tensor& g_quats,
                                                             const at::Tensor& g_rots) {
  check_inputs(means, quats, blended);
  const auto m = means.contiguous(), q = quats.contiguous(), a = blended.contiguous();
  const auto gp = g_posed.to(m.scalar_type()).contiguous(), gq = g_quats.to(m.scalar_type()).contiguous(),
             gr = g_rots.to(m.scalar_type()).contiguous();
  const int64_t N = m.size(0);
  auto d_means = at::empty({N, 3}, m.options());
  auto d_quats = at::empty({N, 4}, m.options());
  auto d_blended = at::empty({N, 12}, m.options());
  AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "eva_skinning_backward", [&] {
    skin_backward_kernel<scalar_t>(m.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(), N, eps,
                                   gp.data_ptr<scalar_t>(), gq.data_ptr<scalar_t>(), gr.data_ptr<scalar_t>(),
                                   d_means.data_ptr<scalar_t>(), d_quats.data_ptr<scalar_t>(),
                                   d_blended.data_ptr<scalar_t>());
  });
  return {d_means, d_quats, d_blended};
}

}  // namespace

TORCH_LIBRARY(eva_skinning, m) {
  m.def("skin_forward", &skin_forward);
  m.def("skin_backward", &skin_backward);
}
