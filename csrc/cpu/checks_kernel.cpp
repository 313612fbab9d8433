// value_flags on CPU: NaN/inf and range checks, parallel over chunks of each tensor.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/zeros.h>

#include <atomic>
#include <cmath>

#include "lidarops/checks.h"
#include "lidarops/common.h"

namespace lidarops {
namespace {

constexpr int64_t kGrain = 1 << 15;

bool any_nonfinite(const at::Tensor& t_in) {
  if (t_in.numel() == 0) return false;
  auto t = t_in.contiguous();
  std::atomic<bool> bad{false};
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, t.scalar_type(), "value_flags_finite", [&] {
    const scalar_t* p = t.data_ptr<scalar_t>();
    at::parallel_for(0, t.numel(), kGrain, [&](int64_t s, int64_t e) {
      if (bad.load(std::memory_order_relaxed)) return;
      bool local = false;
      for (int64_t i = s; i < e; ++i) local |= !std::isfinite(static_cast<double>(p[i]));
      if (local) bad.store(true, std::memory_order_relaxed);
    });
  });
  return bad.load();
}

bool any_outside(const at::Tensor& t_in, int64_t lo, int64_t hi) {
  if (t_in.numel() == 0) return false;
  auto t = t_in.contiguous();
  std::atomic<bool> bad{false};
  AT_DISPATCH_INTEGRAL_TYPES(t.scalar_type(), "value_flags_range", [&] {
    const scalar_t* p = t.data_ptr<scalar_t>();
    at::parallel_for(0, t.numel(), kGrain, [&](int64_t s, int64_t e) {
      if (bad.load(std::memory_order_relaxed)) return;
      bool local = false;
      for (int64_t i = s; i < e; ++i) {
        const int64_t v = static_cast<int64_t>(p[i]);
        local |= v < lo || v > hi;
      }
      if (local) bad.store(true, std::memory_order_relaxed);
    });
  });
  return bad.load();
}

at::Tensor value_flags_cpu(at::TensorList finite, at::TensorList ranged, at::IntArrayRef lo, at::IntArrayRef hi) {
  check_value_flags_args(finite, ranged, lo, hi, c10::Device(c10::kCPU));
  auto flags = at::zeros({static_cast<int64_t>(finite.size() + ranged.size())}, at::dtype(at::kInt));
  int32_t* f = flags.data_ptr<int32_t>();
  for (size_t i = 0; i < finite.size(); ++i) f[i] = any_nonfinite(finite[i]);
  for (size_t j = 0; j < ranged.size(); ++j) f[finite.size() + j] = any_outside(ranged[j], lo[j], hi[j]);
  return flags;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CPU, m) { m.impl("value_flags", &value_flags_cpu); }

}  // namespace lidarops
