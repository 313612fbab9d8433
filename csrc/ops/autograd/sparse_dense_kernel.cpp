// Autograd kernels of lidarops::sparse_to_dense and lidarops::sparse_from_dense, in C++ like
// sparse_conv's (csrc/ops/autograd/sparse_conv_kernel.cpp): every SparseConvTensor.dense() and ToDense
// calls them, and a Python autograd kernel cost each call its host time, gradients or not.
// The two are adjoint linear maps (a scatter to unique sites and the gather from them): each one's
// backward is the other, so both differentiate any number of times.
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/autograd.h>
#include <torch/library.h>

namespace lidarops {
namespace sparse {
namespace {

at::Tensor to_dense_op(const at::Tensor& features, const at::Tensor& indices, int64_t batch_size,
                       at::IntArrayRef spatial_shape) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_to_dense", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&, int64_t, at::IntArrayRef)>();
  return op.call(features, indices, batch_size, spatial_shape);
}

at::Tensor from_dense_op(const at::Tensor& dense, const at::Tensor& indices) {
  static auto op = c10::Dispatcher::singleton()
                       .findSchemaOrThrow("lidarops::sparse_from_dense", "")
                       .typed<at::Tensor(const at::Tensor&, const at::Tensor&)>();
  return op.call(dense, indices);
}

class ToDenseFunction : public torch::autograd::Function<ToDenseFunction> {
 public:
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& features,
                            const at::Tensor& indices, int64_t batch_size, at::IntArrayRef spatial_shape) {
    at::AutoDispatchBelowADInplaceOrView below;
    ctx->save_for_backward({indices});
    return to_dense_op(features, indices, batch_size, spatial_shape);
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 const torch::autograd::variable_list& grads) {
    at::Tensor grad_features;
    if (ctx->needs_input_grad(0)) grad_features = from_dense_op(grads[0], ctx->get_saved_variables()[0]);
    return {grad_features, at::Tensor(), at::Tensor(), at::Tensor()};
  }
};

class FromDenseFunction : public torch::autograd::Function<FromDenseFunction> {
 public:
  static at::Tensor forward(torch::autograd::AutogradContext* ctx, const at::Tensor& dense, const at::Tensor& indices) {
    at::AutoDispatchBelowADInplaceOrView below;
    ctx->save_for_backward({indices});
    ctx->saved_data["batch_size"] = dense.size(0);
    ctx->saved_data["spatial_shape"] = dense.sizes().slice(2).vec();
    return from_dense_op(dense, indices);
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 const torch::autograd::variable_list& grads) {
    at::Tensor grad_dense;
    if (ctx->needs_input_grad(0)) {
      const auto shape = ctx->saved_data["spatial_shape"].toIntVector();
      grad_dense = to_dense_op(grads[0].contiguous(), ctx->get_saved_variables()[0],
                               ctx->saved_data["batch_size"].toInt(), shape);
    }
    return {grad_dense, at::Tensor()};
  }
};

at::Tensor sparse_to_dense_autograd(const at::Tensor& features, const at::Tensor& indices, int64_t batch_size,
                                    at::IntArrayRef spatial_shape) {
  return ToDenseFunction::apply(features, indices, batch_size, spatial_shape);
}

at::Tensor sparse_from_dense_autograd(const at::Tensor& dense, const at::Tensor& indices) {
  return FromDenseFunction::apply(dense, indices);
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, Autograd, m) {
  m.impl("sparse_to_dense", &sparse_to_dense_autograd);
  m.impl("sparse_from_dense", &sparse_from_dense_autograd);
}

}  // namespace sparse
}  // namespace lidarops
