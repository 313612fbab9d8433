// Argument checks of the value_flags op, shared by its CPU and CUDA kernels.
#pragma once

#include <ATen/core/Tensor.h>

namespace lidarops {

// Checks shapes and devices of value_flags' arguments; returns the device of the flags.
inline c10::Device check_value_flags_args(at::TensorList finite, at::TensorList ranged, at::IntArrayRef lo,
                                          at::IntArrayRef hi, c10::Device fallback) {
  TORCH_CHECK_VALUE(lo.size() == ranged.size() && hi.size() == ranged.size(), "value_flags: lo and hi must have ",
                    ranged.size(), " entries (one per ranged tensor), got ", lo.size(), " and ", hi.size());
  c10::Device device = fallback;
  bool first = true;
  auto see = [&](const at::Tensor& t, const char* what, size_t i) {
    if (first) device = t.device();
    first = false;
    TORCH_CHECK_VALUE(t.device() == device, "value_flags: ", what, "[", i, "] is on ", t.device(), " but the first tensor is on ",
                      device);
  };
  for (size_t i = 0; i < finite.size(); ++i) {
    see(finite[i], "finite", i);
    TORCH_CHECK_VALUE(at::isFloatingType(finite[i].scalar_type()), "value_flags: finite[", i, "] must be floating, got ",
                      finite[i].scalar_type());
  }
  for (size_t j = 0; j < ranged.size(); ++j) {
    see(ranged[j], "ranged", j);
    TORCH_CHECK_VALUE(at::isIntegralType(ranged[j].scalar_type(), /*includeBool=*/false), "value_flags: ranged[", j,
                      "] must be an integer tensor, got ", ranged[j].scalar_type());
    TORCH_CHECK_VALUE(lo[j] <= hi[j], "value_flags: lo[", j, "] = ", lo[j], " > hi[", j, "] = ", hi[j]);
  }
  return device;
}

}  // namespace lidarops
