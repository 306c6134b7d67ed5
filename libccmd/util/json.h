#pragma once

// A small JSON value for reports, stats files and tests: build, serialise, parse.
// Parsing is bounded (depth and size) and returns errors, never throws.

#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

class Json {
 public:
  using Array = std::vector<Json>;
  using Object = std::map<std::string, Json>;

  Json() = default;  // null
  Json(std::nullptr_t) {}
  Json(bool b) : value_(b) {}
  Json(int v) : value_(static_cast<double>(v)) {}
  Json(long v) : value_(static_cast<double>(v)) {}
  Json(long long v) : value_(static_cast<double>(v)) {}
  Json(unsigned v) : value_(static_cast<double>(v)) {}
  Json(unsigned long v) : value_(static_cast<double>(v)) {}
  Json(unsigned long long v) : value_(static_cast<double>(v)) {}
  Json(double v) : value_(v) {}
  Json(const char* s) : value_(std::string(s)) {}
  Json(std::string s) : value_(std::move(s)) {}
  Json(Array a) : value_(std::move(a)) {}
  Json(Object o) : value_(std::move(o)) {}

  static Json MakeArray() { return Json(Array{}); }
  static Json MakeObject() { return Json(Object{}); }

  bool is_null() const { return std::holds_alternative<std::monostate>(value_); }
  bool is_bool() const { return std::holds_alternative<bool>(value_); }
  bool is_number() const { return std::holds_alternative<double>(value_); }
  bool is_string() const { return std::holds_alternative<std::string>(value_); }
  bool is_array() const { return std::holds_alternative<Array>(value_); }
  bool is_object() const { return std::holds_alternative<Object>(value_); }

  // Typed access; wrong types return the fallback.
  double number(double fallback = 0.0) const;
  bool boolean(bool fallback = false) const;
  const std::string& string() const;
  const Array& array() const;
  const Object& object() const;

  // Object access: operator[] inserts (turning null into an object); Get does not.
  Json& operator[](const std::string& key);
  const Json* Get(const std::string& key) const;
  bool Has(const std::string& key) const { return Get(key) != nullptr; }
  // Array append (turning null into an array).
  void Push(Json value);
  std::size_t size() const;
  const Json& at(std::size_t i) const { return array()[i]; }

  // indent < 0: compact; otherwise pretty with that many spaces.
  std::string Dump(int indent = 2) const;

  static StatusOr<Json> Parse(std::string_view text);

 private:
  void DumpTo(std::string* out, int indent, int level) const;
  std::variant<std::monostate, bool, double, std::string, Array, Object> value_;
};

// Writes a JSON file atomically.
Status WriteJsonFile(const Json& json, const std::string& path);
StatusOr<Json> ReadJsonFile(const std::string& path);

}  // namespace ccmd
