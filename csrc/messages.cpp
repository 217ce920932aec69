// The static fields of the messages (messages.h): what the operators accept,
// as the messages spell it, from the one definition of each fact.
#include "messages.h"

#include <c10/core/ScalarType.h>
#include <c10/util/StringUtil.h>

#include <string>
#include <vector>

#include "fit_rotation.h"
#include "limits.h"

namespace torchrot {
namespace messages {
namespace {

// "a, b or c" (or_word: "or") / "a, b, c" (or_word: nullptr).
std::string listed(const std::vector<std::string>& items, const char* or_word) {
  std::string text;
  for (size_t i = 0; i < items.size(); ++i) {
    if (i > 0) text += (or_word != nullptr && i + 1 == items.size()) ? std::string(" ") + or_word + " " : ", ";
    text += items[i];
  }
  return text;
}

std::vector<std::pair<std::string, std::string>> make_static_fields() {
  std::vector<std::string> dtypes, variants, kernels;
  for (const at::ScalarType dtype : kSupportedDtypes) dtypes.emplace_back(std::string(c10::getDtypeNames(dtype).first));
  for (const VariantName& variant : kVariantNames) variants.push_back(std::string("'") + variant.name + "'");
  for (const char* kernel : kCpuKernelNames) kernels.emplace_back(kernel);
  return {
      {"dtypes", listed(dtypes, "or")},
      {"variants", listed(variants, nullptr)},
      {"cpu_kernels", listed(kernels, nullptr)},
      {"max_iter", c10::str(limits::kMaxIter)},
      {"max_gradient_eps", c10::str(limits::kMaxGradientEps)},
      {"init_tolerance", c10::str(limits::kInitTolerance)},
  };
}

const std::vector<std::pair<std::string, std::string>>& static_fields() {
  static const auto fields = make_static_fields();
  return fields;
}

void fill(std::string& text, const std::string& key, const std::string& value) {
  const std::string field = "{" + key + "}";
  for (size_t at = text.find(field); at != std::string::npos; at = text.find(field, at + value.size())) {
    text.replace(at, field.size(), value);
  }
}

}  // namespace

std::string format(const Message& message, std::initializer_list<std::pair<const char*, std::string>> fields) {
  std::string text = message.text;
  for (const auto& [key, value] : static_fields()) fill(text, key, value);
  for (const auto& [key, value] : fields) fill(text, key, value);
  return text;
}

}  // namespace messages
}  // namespace torchrot
