#include "libccmd/util/options_writer.h"

#include <cmath>
#include <cstdio>
#include <cstdlib>

namespace ccmd {

void OptionsWriter::Add(std::string_view name, bool value) {
  AddText(name, value ? "true" : "false");
}

void OptionsWriter::Add(std::string_view name, double value) {
  if (!std::isfinite(value)) {
    AddText(name, std::isnan(value) ? "nan" : (value > 0 ? "inf" : "-inf"));
    return;
  }
  // Shortest text that reads back as the same double.
  char text[32];
  for (int digits = 6; digits <= 17; ++digits) {
    std::snprintf(text, sizeof(text), "%.*g", digits, value);
    if (std::strtod(text, nullptr) == value) break;
  }
  AddText(name, text);
}

void OptionsWriter::Add(std::string_view name, std::string_view value) {
  std::string quoted = "\"";
  for (char c : value) {
    if (c == '"' || c == '\\') quoted.push_back('\\');
    quoted.push_back(c);
  }
  AddText(name, quoted + "\"");
}

void OptionsWriter::AddText(std::string_view name, std::string text) {
  entries_.emplace_back(prefix_ + std::string(name), std::move(text));
}

std::string OptionsWriter::ToString() const {
  std::string text;
  for (const auto& [name, value] : entries_) text += name + " = " + value + "\n";
  return text;
}

}  // namespace ccmd
