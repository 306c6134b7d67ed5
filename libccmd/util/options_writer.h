#pragma once

// One way for every options struct to show its values. Each struct has
//   Status Validate() const;                      // clear error for a bad value
//   void Describe(OptionsWriter* out) const;      // every field, by name
// and programs log DescribeOptions(options) at start-up, so a run's log says exactly what it ran
// with.
//
//   void DenseMapOptions::Describe(OptionsWriter* out) const {
//     out->Add("voxel_size_m", voxel_size_m);
//     out->Nested("projection", projection);   // "projection.min_depth_m = 0.3", ...
//   }

#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <vector>

#include "libccmd/util/ids.h"
#include "libccmd/util/logging.h"

namespace ccmd {

class OptionsWriter {
 public:
  void Add(std::string_view name, bool value);
  void Add(std::string_view name, double value);
  void Add(std::string_view name, std::string_view value);
  void Add(std::string_view name, const char* value) { Add(name, std::string_view(value)); }
  void Add(std::string_view name, const std::string& value) { Add(name, std::string_view(value)); }
  template <typename T,
            typename = std::enable_if_t<std::is_integral_v<T> && !std::is_same_v<T, bool>>>
  void Add(std::string_view name, T value) {
    AddText(name, std::to_string(value));
  }
  void Add(std::string_view name, float value) { Add(name, static_cast<double>(value)); }
  template <typename Tag, typename Rep>
  void Add(std::string_view name, TypedId<Tag, Rep> id) {
    Add(name, id.value());
  }
  template <typename T>
  void Add(std::string_view name, const std::vector<T>& values) {
    OptionsWriter items;
    for (const T& v : values) items.Add("", v);
    std::string text = "[";
    for (size_t i = 0; i < items.entries_.size(); ++i) {
      text += (i ? ", " : "") + items.entries_[i].second;
    }
    AddText(name, text + "]");
  }

  // The fields of a nested options struct, named "name.field".
  template <typename Options>
  void Nested(std::string_view name, const Options& options) {
    const size_t saved = prefix_.size();
    prefix_.append(name).push_back('.');
    options.Describe(this);
    prefix_.resize(saved);
  }

  // (full name, value as text), in the order they were added.
  const std::vector<std::pair<std::string, std::string>>& entries() const { return entries_; }

  // "name = value", one per line.
  std::string ToString() const;

 private:
  void AddText(std::string_view name, std::string text);

  std::string prefix_;
  std::vector<std::pair<std::string, std::string>> entries_;
};

template <typename Options>
std::string DescribeOptions(const Options& options) {
  OptionsWriter out;
  options.Describe(&out);
  return out.ToString();
}

// Logs every value at INFO, one line each, named "what.field": a program's start-up record.
template <typename Options>
void LogOptions(std::string_view what, const Options& options) {
  OptionsWriter out;
  options.Describe(&out);
  for (const auto& [name, value] : out.entries())
    CCMD_LOG(INFO) << what << "." << name << " = " << value;
}

}  // namespace ccmd
