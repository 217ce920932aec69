#include "warm_starts.h"

#include "checks.h"
#include "layout.h"

namespace torchrot {
namespace ops {

WarmStartCount count_bad_warm_starts(const at::Tensor& init, at::ScalarType compute) {
  const int64_t n = init.numel() / 9;
  if (n == 0) return {};
  at::Tensor keep;
  return count_bad_warm_starts_cpu(compute, n, broadcast_view(init, init.sizes(), n, compute, keep));
}

bool check_warm_starts(const at::Tensor& init, at::ScalarType compute) {
  const WarmStartCount count = count_bad_warm_starts(init, compute);
  if (count.bad != 0) throw_bad_init(count.bad, init.numel() / 9);
  return count.unclean == 0;
}

}  // namespace ops
}  // namespace torchrot
