// Kernel-map (rulebook) construction for sparse convolution on CUDA. Same results as the CPU kernels
// (csrc/cpu/sparse_kernel_map_kernel.cpp):
//   - output sites: marked in a dense byte grid and listed by at::nonzero (sorted), or inserted into a
//     hash set (atomicCAS) and sorted; either way sorted by linear key, identical to the CPU order;
//   - kernel map: input coordinates go into a dense index grid (atomicCAS on int32 slots) or an
//     open-addressing hash table (atomicCAS on 64-bit keys, linear probing, capacity >= 2N); one
//     thread per (output row, kernel offset) looks its input up.
// Validation (coordinates outside the grid, duplicates) is flagged on the device and costs one host
// sync per map (or a read after the caller's next launches: sparse_kernel_map_deferred); when a flag is
// set, the message is produced by the CPU checks on a host copy, so it names the same rows as on CPU.
// Without validation (the sparse layers skip it for sites they checked or produced) no flag is kept and
// bad rows are skipped.
#include <ATen/ATen.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <mutex>
#include <tuple>
#include <utility>

#include "lidarops/cuda_launch.cuh"
#include "lidarops/sparse.h"

namespace lidarops {
namespace sparse {
namespace {

constexpr int kThreads = 256;

inline int64_t blocks_for(int64_t n) { return std::max<int64_t>(1, gpu::ceil_div(n, kThreads)); }

// A new tensor with every byte set to `byte` (0, or 0xFF for -1 in any integer width): one cudaMemsetAsync,
// less host time per map than at::full's fill kernel.
at::Tensor filled(at::IntArrayRef size, const at::TensorOptions& options, int byte) {
  auto t = at::empty(size, options);
  if (t.numel() > 0)
    C10_CUDA_CHECK(cudaMemsetAsync(t.data_ptr(), byte, t.nbytes(), c10::cuda::getCurrentCUDAStream()));
  return t;
}

__device__ __forceinline__ bool row_in_range(const int32_t* r, const ConvGeometry& g) {
  if (r[0] < 0 || r[0] >= g.batch) return false;
  for (int d = 0; d < g.ndim; ++d)
    if (r[d + 1] < 0 || r[d + 1] >= g.in_shape[d]) return false;
  return true;
}

__device__ __forceinline__ int64_t row_key(const int32_t* r, const int64_t* shape, int ndim) {
  int64_t c[kMaxDim];
  for (int d = 0; d < ndim; ++d) c[d] = r[d + 1];
  return site_key(r[0], c, shape, ndim);
}

// flags[0]: smallest row outside the grid (all bits set if none); flags[1]: cleared if a duplicate was seen.
__global__ void check_range_kernel(const int32_t* __restrict__ idx, int64_t n, ConvGeometry g,
                                   unsigned long long* flags) {
  const int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (i >= n) return;
  if (!row_in_range(idx + i * (g.ndim + 1), g)) atomicMin(flags, static_cast<unsigned long long>(i));
}

// flags (may be null: no validation): [0] the smallest bad row, [1] cleared when a duplicate is seen
__device__ __forceinline__ void flag_row(unsigned long long* flags, int64_t i) {
  if (flags != nullptr) atomicMin(flags, static_cast<unsigned long long>(i));
}
__device__ __forceinline__ void flag_duplicate(unsigned long long* flags) {
  if (flags != nullptr) atomicExch(flags + 1, 0ULL);
}

__global__ void insert_dense_kernel(const int32_t* __restrict__ idx, int64_t n, ConvGeometry g, int32_t* grid,
                                    unsigned long long* flags) {
  const int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (i >= n) return;
  const int32_t* r = idx + i * (g.ndim + 1);
  if (!row_in_range(r, g)) {
    flag_row(flags, i);
    return;
  }
  const int64_t key = row_key(r, g.in_shape, g.ndim);
  const int32_t prev = atomicCAS(grid + key, -1, static_cast<int32_t>(i));
  if (prev != -1) flag_duplicate(flags);
}

__device__ __forceinline__ bool hash_insert(unsigned long long* keys, int32_t* vals, uint64_t mask, int64_t key,
                                            int32_t val) {
  uint64_t h = mix64(static_cast<uint64_t>(key)) & mask;
  const unsigned long long empty = static_cast<unsigned long long>(kEmptyKey);
  while (true) {
    const unsigned long long prev = atomicCAS(keys + h, empty, static_cast<unsigned long long>(key));
    if (prev == empty) {
      if (vals != nullptr) vals[h] = val;
      return true;
    }
    if (prev == static_cast<unsigned long long>(key)) return false;
    h = (h + 1) & mask;
  }
}

__global__ void insert_hash_kernel(const int32_t* __restrict__ idx, int64_t n, ConvGeometry g, unsigned long long* keys,
                                   int32_t* vals, uint64_t mask, unsigned long long* flags) {
  const int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (i >= n) return;
  const int32_t* r = idx + i * (g.ndim + 1);
  if (!row_in_range(r, g)) {
    flag_row(flags, i);
    return;
  }
  if (!hash_insert(keys, vals, mask, row_key(r, g.in_shape, g.ndim), static_cast<int32_t>(i)))
    flag_duplicate(flags);
}

// One thread per (input row, kernel offset): mark (dense byte grid) or insert (hash set) the output site.
template <bool kDense>
__global__ void mark_outputs_kernel(const int32_t* __restrict__ idx, int64_t n, ConvGeometry g, uint8_t* mark,
                                    unsigned long long* keys, uint64_t mask) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t >= n * g.kvol) return;
  const int64_t i = t / g.kvol, k = t % g.kvol;
  const int32_t* r = idx + i * (g.ndim + 1);
  if (!row_in_range(r, g)) return;  // reached only without validation: such rows are skipped
  int64_t p[kMaxDim], q[kMaxDim], off[kMaxDim];
  for (int d = 0; d < g.ndim; ++d) p[d] = r[d + 1];
  kernel_offsets(g, k, off);
  if (!output_of_input(g, p, off, q)) return;
  const int64_t key = site_key(r[0], q, g.out_shape, g.ndim);
  if (kDense) mark[key] = 1;  // benign race: every writer stores the same byte
  else hash_insert(keys, nullptr, mask, key, 0);
}

__global__ void decode_keys_kernel(const int64_t* __restrict__ keys, int64_t m, ConvGeometry g, int32_t* out) {
  const int64_t j = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (j >= m) return;
  int32_t* r = out + j * (g.ndim + 1);
  if (keys[j] < 0) {  // nonzero_static's padding (sites that broke the vouch): outside every grid
    for (int d = 0; d <= g.ndim; ++d) r[d] = -1;
    return;
  }
  int64_t b, c[kMaxDim];
  decode_key(keys[j], g.out_shape, g.ndim, &b, c);
  r[0] = static_cast<int32_t>(b);
  for (int d = 0; d < g.ndim; ++d) r[d + 1] = static_cast<int32_t>(c[d]);
}

// A deferred site check's word (DeferredChecks): the table's flags, final once the fill has run, folded into
// one word of pinned host memory, written whole so that the host never reads half of it.
struct CheckWord {
  const unsigned long long* flags = nullptr;
  unsigned long long* word = nullptr;  // nullptr: no deferred check
  unsigned long long value = 0;        // ticket << 2
};

__global__ void lookup_kernel(const int32_t* __restrict__ out_idx, int64_t m, ConvGeometry g, TableView table,
                              int32_t* __restrict__ nbr, CheckWord check) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t == 0 && check.word != nullptr) {
    *reinterpret_cast<volatile unsigned long long*>(check.word) =
        check.value | (check.flags[0] != ~0ULL ? 1ULL : 0ULL) | (check.flags[1] != ~0ULL ? 2ULL : 0ULL);
  }
  if (t >= m * g.kvol) return;
  const int64_t o = t / g.kvol, k = t % g.kvol;
  const int32_t* r = out_idx + o * (g.ndim + 1);
  int32_t result = -1;
  const int64_t b = r[0];
  if (b >= 0 && b < g.batch) {
    int64_t q[kMaxDim], p[kMaxDim], off[kMaxDim];
    for (int d = 0; d < g.ndim; ++d) q[d] = r[d + 1];
    kernel_offsets(g, k, off);
    if (input_of_output(g, q, off, p)) result = table.find(site_key(b, p, g.in_shape, g.ndim));
  }
  nbr[t] = result;
}

__global__ void transpose_kernel(const int32_t* __restrict__ nbr, int64_t m, int64_t K, int64_t n_in,
                                 int32_t* __restrict__ out) {
  const int64_t t = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (t >= m * K) return;
  const int32_t i = nbr[t];
  if (i >= 0 && i < n_in) out[static_cast<int64_t>(i) * K + t % K] = static_cast<int32_t>(t / K);
}

// Raise the CPU's message for the rows flagged on the device (a row outside the grid, a duplicate).
void raise_for_flags(bool bad_range, bool dup, const at::Tensor& idx, const ConvGeometry& g) {
  if (!bad_range && !dup) return;
  const auto cpu = idx.cpu();
  raise_if_out_of_range(cpu, "indices", g.batch, g.in_shape, g.ndim);
  raise_if_duplicates(cpu, "indices", g.batch, g.in_shape, g.ndim);
  TORCH_CHECK_VALUE(false, "indices hold duplicate coordinates; a sparse tensor needs unique coordinates");
}

// ... read now (one host sync).
void raise_flags(const at::Tensor& flags, const at::Tensor& idx, const ConvGeometry& g, bool check_dups) {
  const auto host = flags.cpu();
  const auto* f = reinterpret_cast<const unsigned long long*>(host.data_ptr<int64_t>());
  raise_for_flags(f[0] != ~0ULL, check_dups && f[1] != ~0ULL, idx, g);
}

// A map's site check read later: the map's last kernel (the lookup) writes one word per check into a ring of
// pinned, device-mapped host slots, ticket << 2 plus the flags' bits (1: a row outside the grid, 2: a repeated
// site). The caller reads it once the work that follows is queued, in the slot itself
// (sparse_site_check_slots) or through sparse_site_check, which waits for the word and raises: the host
// neither waits for the map nor issues a copy or an event for its check.
class DeferredChecks {
 public:
  static constexpr int64_t kSlots = 64;

  // The next ticket and the device address of its slot.
  std::pair<int64_t, unsigned long long*> issue(cudaStream_t stream) {
    std::lock_guard<std::mutex> lock(mu_);
    allocate();
    const int64_t ticket = next_++;
    const int64_t i = ticket % kSlots;
    // the slot's last word must land before the slot is reused (a kernel that never ran writes nothing)
    if (slots_[i].ticket >= 0) wait(i, /*must_land=*/false);
    slots_[i] = {ticket, stream};
    return {ticket, device_ + i};
  }

  // A ticket whose kernel was never launched: its slot is free at once.
  void forget(int64_t ticket) {
    std::lock_guard<std::mutex> lock(mu_);
    if (slots_[ticket % kSlots].ticket == ticket) slots_[ticket % kSlots].ticket = -1;
  }

  // The flags' bits of ticket (waits for its word).
  unsigned long long redeem(int64_t ticket) {
    std::lock_guard<std::mutex> lock(mu_);
    const int64_t i = ticket % kSlots;
    TORCH_CHECK_VALUE(ticket >= 0 && ticket < next_ && slots_[i].ticket == ticket, "site-check ticket ", ticket,
                      " is unknown or its slot was reused (tickets come from sparse_kernel_map_deferred; the last ",
                      kSlots, " issued can be read)");
    wait(i, /*must_land=*/true);
    return word(i) & 3ULL;
  }

  // The ring as a CPU tensor over the pinned slots, for a caller's own read of a word.
  at::Tensor slots() {
    std::lock_guard<std::mutex> lock(mu_);
    allocate();
    return at::from_blob(host_, {kSlots}, at::TensorOptions().dtype(at::kLong));
  }

 private:
  struct Slot {
    int64_t ticket = -1;  // the last ticket issued on the slot
    cudaStream_t stream = nullptr;
  };

  void allocate() {
    if (host_ != nullptr) return;
    void* p = nullptr;
    C10_CUDA_CHECK(cudaHostAlloc(&p, sizeof(unsigned long long) * kSlots, cudaHostAllocPortable | cudaHostAllocMapped));
    host_ = static_cast<unsigned long long*>(p);
    for (int64_t i = 0; i < kSlots; ++i) host_[i] = ~0ULL;  // no ticket's word
    void* d = nullptr;
    C10_CUDA_CHECK(cudaHostGetDevicePointer(&d, p, 0));
    device_ = static_cast<unsigned long long*>(d);
  }

  unsigned long long word(int64_t i) const { return *reinterpret_cast<volatile const unsigned long long*>(host_ + i); }
  bool landed(int64_t i) const { return (word(i) >> 2) == static_cast<unsigned long long>(slots_[i].ticket); }

  // Polled, not an event's synchronize (the word has usually landed); an idle stream whose word never came
  // means its kernel did not run: an error for a read, a free slot for a reuse.
  void wait(int64_t i, bool must_land) const {
    for (int64_t spins = 1; !landed(i); ++spins) {
      if (spins % 256 != 0) continue;
      const cudaError_t status = cudaStreamQuery(slots_[i].stream);
      if (status == cudaErrorNotReady) continue;
      C10_CUDA_CHECK(status);
      if (landed(i) || !must_land) return;
      TORCH_CHECK(false, "the site check of ticket ", slots_[i].ticket, " was never written: its map's kernel did "
                  "not run");
    }
  }

  std::mutex mu_;
  unsigned long long* host_ = nullptr;    // kSlots words; pinned, never freed (process lifetime)
  unsigned long long* device_ = nullptr;  // the same words' device address
  Slot slots_[kSlots];
  int64_t next_ = 0;
};

DeferredChecks& deferred_checks() {
  static DeferredChecks* checks = new DeferredChecks();  // never destroyed: no CUDA calls at process exit
  return *checks;
}

// Both flags start with all bits set: "no bad row" for atomicMin on unsigned, "no duplicate" (one fill).
at::Tensor new_flags(const at::Tensor& like) { return filled({2}, like.options().dtype(at::kLong), 0xFF); }

unsigned long long* flag_ptr(const at::Tensor& flags) {
  return reinterpret_cast<unsigned long long*>(flags.data_ptr<int64_t>());
}

struct DeviceTable {
  at::Tensor dense, keys, vals;
  at::Tensor flags;  // the site check's two flags (validated tables)
  int64_t mask = 0;
  TableView view() const {
    TableView v;
    if (dense.defined()) {
      v.dense = dense.data_ptr<int32_t>();
    } else {
      v.keys = keys.data_ptr<int64_t>();
      v.vals = vals.data_ptr<int32_t>();
      v.mask = mask;
    }
    return v;
  }
};

// validate: the rows outside the grid and the duplicates are flagged in two int64 slots kept at the end of the
// table's own fill (no launch of their own), which the table's -1 fill already sets to "none"; then raised
// here (one host sync) unless defer (the caller has them read later: DeferredChecks).
DeviceTable build_table_cuda(const at::Tensor& idx, const ConvGeometry& g, int64_t method, bool validate,
                             bool defer = false) {
  const int64_t n = idx.size(0);
  TORCH_CHECK_VALUE(n < INT32_MAX, "indices has ", n, " rows; at most 2^31 - 2 are supported");
  auto stream = c10::cuda::getCurrentCUDAStream();
  DeviceTable t;
  at::Tensor& flags = t.flags;
  const int64_t cells = grid_cells(g.batch, g.in_shape, g.ndim);
  if (use_dense_table(cells, n, method)) {
    const int64_t at_flags = cells + (cells & 1);  // 8-byte aligned: two int64 slots over four int32 ones
    t.dense = filled({validate ? at_flags + 4 : cells}, idx.options().dtype(at::kInt), 0xFF);
    if (validate) flags = t.dense.narrow(0, at_flags, 4).view(at::kLong);
    insert_dense_kernel<<<blocks_for(n), kThreads, 0, stream>>>(idx.data_ptr<int32_t>(), n, g,
                                                                t.dense.data_ptr<int32_t>(),
                                                                validate ? flag_ptr(flags) : nullptr);
  } else {
    const int64_t cap = hash_capacity(n);
    t.mask = cap - 1;
    t.keys = filled({validate ? cap + 2 : cap}, idx.options().dtype(at::kLong), 0xFF);
    static_assert(kEmptyKey == -1, "the flags' \"none\" is the empty key's fill");
    if (validate) flags = t.keys.narrow(0, cap, 2);
    t.vals = filled({cap}, idx.options().dtype(at::kInt), 0xFF);
    insert_hash_kernel<<<blocks_for(n), kThreads, 0, stream>>>(
        idx.data_ptr<int32_t>(), n, g, reinterpret_cast<unsigned long long*>(t.keys.data_ptr<int64_t>()),
        t.vals.data_ptr<int32_t>(), static_cast<uint64_t>(t.mask), validate ? flag_ptr(flags) : nullptr);
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (validate && !defer) raise_flags(flags, idx, g, /*check_dups=*/true);
  return t;
}

// A transposed convolution whose kernel is its stride, without padding or dilation, on an output grid that holds
// every input's block: distinct input sites reach disjoint blocks of K output sites, so N checked sites reach N K.
bool disjoint_blocks(const ConvGeometry& g) {
  if (!g.transposed) return false;
  for (int d = 0; d < g.ndim; ++d)
    if (g.kernel[d] != g.stride[d] || g.pad[d] != 0 || g.dil[d] != 1 || g.out_shape[d] < g.in_shape[d] * g.stride[d])
      return false;
  return true;
}

at::Tensor sparse_conv_out_indices_cuda(const at::Tensor& indices_in, int64_t batch_size, at::IntArrayRef spatial_shape,
                                        at::IntArrayRef out_spatial_shape, at::IntArrayRef kernel_size,
                                        at::IntArrayRef stride, at::IntArrayRef padding, at::IntArrayRef dilation,
                                        bool transposed, int64_t method, bool validate, bool checked) {
  TORCH_CHECK_VALUE(!out_spatial_shape.empty(), "out_spatial_shape must be given");
  const ConvGeometry g = make_geometry(batch_size, spatial_shape, out_spatial_shape, kernel_size, stride, padding,
                                       dilation, transposed);
  check_indices(indices_in, "indices", g.ndim);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (dense) or 2 (hash), got ", method);
  const c10::cuda::OptionalCUDAGuard guard(indices_in.device());
  auto idx = indices_in.contiguous();
  const int64_t n = idx.size(0), K = g.kvol;
  if (n == 0) return at::empty({0, g.ndim + 1}, idx.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  if (validate) {  // out-of-range input rows: the CPU's error (one sync); without validation they are skipped
    auto flags = new_flags(idx);
    check_range_kernel<<<blocks_for(n), kThreads, 0, stream>>>(idx.data_ptr<int32_t>(), n, g, flag_ptr(flags));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    raise_flags(flags, idx, g, /*check_dups=*/false);
  }
  const int64_t cells = grid_cells(g.batch, g.out_shape, g.ndim);
  at::Tensor keys;
  if (use_dense_table(cells, n, method)) {
    auto mark = filled({cells}, idx.options().dtype(at::kByte), 0);
    mark_outputs_kernel<true><<<blocks_for(n * K), kThreads, 0, stream>>>(idx.data_ptr<int32_t>(), n, g,
                                                                          mark.data_ptr<uint8_t>(), nullptr, 0);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    if (checked && disjoint_blocks(g)) {  // N K outputs, known without reading a count (-1 rows past those found)
      TORCH_CHECK_VALUE(n * K < INT32_MAX, "the convolution has ", n * K, " output sites; at most 2^31 - 2 are supported");
      keys = at::nonzero_static(mark, n * K, -1).view({-1});  // sorted ascending, then the padding
    } else {
      keys = at::nonzero(mark).view({-1});  // sorted ascending
    }
  } else {
    const int64_t cap = hash_capacity(n * K);
    auto set = filled({cap}, idx.options().dtype(at::kLong), 0xFF);
    mark_outputs_kernel<false><<<blocks_for(n * K), kThreads, 0, stream>>>(
        idx.data_ptr<int32_t>(), n, g, nullptr, reinterpret_cast<unsigned long long*>(set.data_ptr<int64_t>()),
        static_cast<uint64_t>(cap - 1));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    keys = std::get<0>(at::sort(set.masked_select(set != kEmptyKey)));
  }
  const int64_t m = keys.numel();
  TORCH_CHECK_VALUE(m < INT32_MAX, "the convolution has ", m, " output sites; at most 2^31 - 2 are supported");
  auto out = at::empty({m, g.ndim + 1}, idx.options());
  if (m > 0) {
    decode_keys_kernel<<<blocks_for(m), kThreads, 0, stream>>>(keys.contiguous().data_ptr<int64_t>(), m, g,
                                                               out.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return out;
}

at::Tensor kernel_map_cuda(const at::Tensor& indices_in, const at::Tensor& out_indices_in, int64_t batch_size,
                           at::IntArrayRef spatial_shape, at::IntArrayRef kernel_size, at::IntArrayRef stride,
                           at::IntArrayRef padding, at::IntArrayRef dilation, bool transposed, bool validate,
                           int64_t method, int64_t* ticket) {
  const ConvGeometry g = make_geometry(batch_size, spatial_shape, {}, kernel_size, stride, padding, dilation, transposed);
  check_indices(indices_in, "indices", g.ndim);
  check_indices(out_indices_in, "out_indices", g.ndim);
  TORCH_CHECK_VALUE(method >= 0 && method <= 2, "method must be 0 (auto), 1 (dense) or 2 (hash), got ", method);
  TORCH_CHECK_VALUE(indices_in.device() == out_indices_in.device(), "out_indices is on ", out_indices_in.device(),
                    " but indices is on ", indices_in.device());
  const c10::cuda::OptionalCUDAGuard guard(indices_in.device());
  auto idx = indices_in.contiguous();
  auto oidx = out_indices_in.contiguous();
  const int64_t m = oidx.size(0), K = g.kvol;
  auto nbr = at::empty({m, K}, idx.options());
  if (m == 0) {  // nothing to pair, but the sites are still checked, at once (a strided layer may reach no output)
    if (validate && idx.size(0) > 0) build_table_cuda(idx, g, method, true);
    return nbr;
  }
  if (idx.size(0) == 0) return nbr.fill_(-1);
  const bool defer = validate && ticket != nullptr;
  const DeviceTable table = build_table_cuda(idx, g, method, validate, defer);
  auto stream = c10::cuda::getCurrentCUDAStream();
  CheckWord check;
  if (defer) {  // the lookup writes the check's word (it runs after the fill that sets the flags)
    const auto issued = deferred_checks().issue(stream.stream());
    *ticket = issued.first;
    check = {flag_ptr(table.flags), issued.second, static_cast<unsigned long long>(issued.first) << 2};
  }
  lookup_kernel<<<blocks_for(m * K), kThreads, 0, stream>>>(oidx.data_ptr<int32_t>(), m, g, table.view(),
                                                            nbr.data_ptr<int32_t>(), check);
  if (defer && cudaPeekAtLastError() != cudaSuccess) deferred_checks().forget(*ticket);  // no word will come
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return nbr;
}

at::Tensor sparse_kernel_map_cuda(const at::Tensor& indices, const at::Tensor& out_indices, int64_t batch_size,
                                  at::IntArrayRef spatial_shape, at::IntArrayRef kernel_size, at::IntArrayRef stride,
                                  at::IntArrayRef padding, at::IntArrayRef dilation, bool transposed, bool validate,
                                  int64_t method) {
  return kernel_map_cuda(indices, out_indices, batch_size, spatial_shape, kernel_size, stride, padding, dilation,
                         transposed, validate, method, nullptr);
}

std::tuple<at::Tensor, int64_t> sparse_kernel_map_deferred_cuda(
    const at::Tensor& indices, const at::Tensor& out_indices, int64_t batch_size, at::IntArrayRef spatial_shape,
    at::IntArrayRef kernel_size, at::IntArrayRef stride, at::IntArrayRef padding, at::IntArrayRef dilation,
    bool transposed, int64_t method) {
  int64_t ticket = -1;  // stays -1 where nothing is checked (no input sites)
  auto nbr = kernel_map_cuda(indices, out_indices, batch_size, spatial_shape, kernel_size, stride, padding, dilation,
                             transposed, /*validate=*/true, method, &ticket);
  return {nbr, ticket};
}

void sparse_site_check_cuda(const at::Tensor& indices, int64_t ticket, int64_t batch_size,
                            at::IntArrayRef spatial_shape) {
  if (ticket < 0) return;
  const unsigned long long bits = deferred_checks().redeem(ticket);
  ConvGeometry g;
  g.ndim = static_cast<int>(spatial_shape.size());
  TORCH_CHECK_VALUE(g.ndim >= 1 && g.ndim <= kMaxDim, "spatial_shape must have 1 to ", kMaxDim, " dimensions, got ",
                    spatial_shape);
  g.batch = batch_size;
  for (int d = 0; d < g.ndim; ++d) g.in_shape[d] = spatial_shape[d];
  raise_for_flags(bits & 1ULL, bits & 2ULL, indices, g);
}

at::Tensor sparse_site_check_slots_cuda(const at::Tensor&) { return deferred_checks().slots(); }

at::Tensor sparse_kernel_map_transpose_cuda(const at::Tensor& nbr_in, int64_t n_in) {
  TORCH_CHECK_VALUE(nbr_in.dim() == 2 && nbr_in.scalar_type() == at::kInt, "kernel_map must be (N_out, K) int32, got shape ",
                    nbr_in.sizes(), " and dtype ", nbr_in.scalar_type());
  TORCH_CHECK_VALUE(n_in >= 0 && n_in < INT32_MAX, "n_in must lie in [0, 2^31 - 1), got ", n_in);
  const c10::cuda::OptionalCUDAGuard guard(nbr_in.device());
  auto nbr = nbr_in.contiguous();
  const int64_t m = nbr.size(0), K = nbr.size(1);
  auto out = filled({n_in, K}, nbr.options(), 0xFF);
  if (m == 0 || n_in == 0 || K == 0) return out;
  // entries outside [-1, n_in) are skipped (no host sync to report them)
  transpose_kernel<<<blocks_for(m * K), kThreads, 0, c10::cuda::getCurrentCUDAStream()>>>(
      nbr.data_ptr<int32_t>(), m, K, n_in, out.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(lidarops, CUDA, m) {
  m.impl("sparse_conv_out_indices", &sparse_conv_out_indices_cuda);
  m.impl("sparse_kernel_map", &sparse_kernel_map_cuda);
  m.impl("sparse_kernel_map_deferred", &sparse_kernel_map_deferred_cuda);
  m.impl("sparse_site_check", &sparse_site_check_cuda);
  m.impl("sparse_site_check_slots", &sparse_site_check_slots_cuda);
  m.impl("sparse_kernel_map_transpose", &sparse_kernel_map_transpose_cuda);
}

}  // namespace sparse
}  // namespace lidarops
