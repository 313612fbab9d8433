// Autograd kernel of lidarops::sparse_conv, in C++ (torchvision's csrc/ops/autograd pattern).
//
// In C++ because a Python autograd kernel (torch.library.register_autograd) puts a Python redispatch in
// front of every call, gradients or not, costing as much host time as a small layer's GPU kernel.
//
//   out[o] = sum_k W[:, k, :] @ x[map[o, k]]
//   d x = sparse_conv(d out, W^T, map^T)   (W^T[ci, k, co] = W[co, k, ci]; map^T from sparse_kernel_map_transpose)
//   d W = sparse_conv_weight_grad(x, d out, map)
// The backward is made of registered ops, so it runs on every device and differentiates again (the
// convolution is bilinear in features and weight); sparse_conv_weight_grad's own formula stays in
// lidarops/sparse/_registrations.py.
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/autograd.h>
#include <torch/library.h>

#include <string>

namespace lidarops {
namespace sparse {
namespace {

at::Tensor conv_op(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& kernel_map,
                   const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_conv", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                         const c10::optional<at::Tensor>&, c10::string_view, int64_t)>();
  return op.call(features, weight, kernel_map, order, algo, splits);
}

at::Tensor transpose_map_op(const at::Tensor& kernel_map, int64_t n_in) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_kernel_map_transpose", "")
                       .typed<at::Tensor(const at::Tensor&, int64_t)>();
  return op.call(kernel_map, n_in);
}

at::Tensor order_op(const at::Tensor& kernel_map) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_kernel_map_order", "")
                       .typed<at::Tensor(const at::Tensor&)>();
  return op.call(kernel_map);
}

at::Tensor weight_grad_op(const at::Tensor& features, const at::Tensor& grad_out, const at::Tensor& kernel_map) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_conv_weight_grad", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&)>();
  return op.call(features, grad_out, kernel_map);
}

class SparseConvFunction : public torch::autograd::Function<SparseConvFunction> {
 public:
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& features,
                            const at::Tensor& weight, const at::Tensor& kernel_map,
                            const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
    at::Tensor out;
    {
      at::AutoDispatchBelowADInplaceOrView below;
      out = conv_op(features, weight, kernel_map, order, algo, splits);
    }
    ctx->save_for_backward({features, weight, kernel_map});
    // the features gradient is the same convolution: it takes the same kernel choice
    ctx->saved_data["algo"] = std::string(algo);
    ctx->saved_data["splits"] = splits;
    return out;
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 const torch::autograd::variable_list& grads) {
    const auto saved = ctx->get_saved_variables();
    const at::Tensor &features = saved[0], &weight = saved[1], &kernel_map = saved[2];
    const at::Tensor grad = grads[0].contiguous();
    at::Tensor grad_x, grad_w;
    if (ctx->needs_input_grad(0)) {
      const at::Tensor map_t = transpose_map_op(kernel_map, features.size(0));
      // the CUDA kernel skips absent offsets per tile when rows are grouped by offset mask; the CPU
      // kernel has no use for an order
      c10::optional<at::Tensor> order_t;
      if (map_t.is_cuda()) order_t = order_op(map_t);
      grad_x = conv_op(grad, weight.permute({2, 1, 0}).contiguous(), map_t, order_t,
                       ctx->saved_data["algo"].toStringRef(), ctx->saved_data["splits"].toInt());
    }
    if (ctx->needs_input_grad(1)) grad_w = weight_grad_op(features, grad, kernel_map);
    return {grad_x, grad_w, at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor()};
  }
};

at::Tensor sparse_conv_autograd(const at::Tensor& features, const at::Tensor& weight, const at::Tensor& kernel_map,
                                const c10::optional<at::Tensor>& order, c10::string_view algo, int64_t splits) {
  return SparseConvFunction::apply(features, weight, kernel_map, order, algo, splits);
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, Autograd, m) { m.impl("sparse_conv", &sparse_conv_autograd); }

}  // namespace sparse
}  // namespace lidarops
