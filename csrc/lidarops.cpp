// The Python module lidarops._C. Importing it runs the static TORCH_LIBRARY registrations of every
// op in this library; the module itself only reports how it was built. It passes no tensors, so it
// needs pybind11 alone, not <torch/extension.h> (the whole torch C++ API: 30 s of compile time).
#include <Python.h>
#include <pybind11/pybind11.h>
#include <torch/version.h>

#include <string>

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "lidarops kernels (registered under torch.ops.lidarops)";
#ifdef WITH_CUDA
  m.attr("with_cuda") = true;
#else
  m.attr("with_cuda") = false;
#endif
  m.attr("torch_version") = std::to_string(TORCH_VERSION_MAJOR) + "." + std::to_string(TORCH_VERSION_MINOR);
}
