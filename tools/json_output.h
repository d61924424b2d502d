// The tools' JSON output, all through nlohmann::json: keys in insertion order, non-finite numbers as
// null and invalid UTF-8 replaced, so no value can break the document.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace prism {

using Json = nlohmann::ordered_json;

// `j` as text and a newline: one line (indent < 0) or indented by `indent` spaces per level.
inline std::string JsonText(const Json& j, int indent = -1) {
  return j.dump(indent, ' ', /*ensure_ascii=*/false, Json::error_handler_t::replace) + "\n";
}

}  // namespace prism
