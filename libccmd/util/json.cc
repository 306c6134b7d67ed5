#include "libccmd/util/json.h"

#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "libccmd/util/file_util.h"

namespace ccmd {

double Json::number(double fallback) const {
  return is_number() ? std::get<double>(value_) : fallback;
}
bool Json::boolean(bool fallback) const { return is_bool() ? std::get<bool>(value_) : fallback; }

const std::string& Json::string() const {
  static const std::string empty;
  return is_string() ? std::get<std::string>(value_) : empty;
}
const Json::Array& Json::array() const {
  static const Array empty;
  return is_array() ? std::get<Array>(value_) : empty;
}
const Json::Object& Json::object() const {
  static const Object empty;
  return is_object() ? std::get<Object>(value_) : empty;
}

Json& Json::operator[](const std::string& key) {
  if (!is_object()) value_ = Object{};
  return std::get<Object>(value_)[key];
}

const Json* Json::Get(const std::string& key) const {
  if (!is_object()) return nullptr;
  const auto& o = std::get<Object>(value_);
  const auto it = o.find(key);
  return it == o.end() ? nullptr : &it->second;
}

void Json::Push(Json value) {
  if (!is_array()) value_ = Array{};
  std::get<Array>(value_).push_back(std::move(value));
}

std::size_t Json::size() const {
  if (is_array()) return std::get<Array>(value_).size();
  if (is_object()) return std::get<Object>(value_).size();
  return 0;
}

namespace {

void EscapeTo(const std::string& s, std::string* out) {
  out->push_back('"');
  for (const unsigned char c : s) {
    switch (c) {
      case '"':
        *out += "\\\"";
        break;
      case '\\':
        *out += "\\\\";
        break;
      case '\n':
        *out += "\\n";
        break;
      case '\r':
        *out += "\\r";
        break;
      case '\t':
        *out += "\\t";
        break;
      default:
        if (c < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof(buf), "\\u%04x", c);
          *out += buf;
        } else {
          out->push_back(static_cast<char>(c));
        }
    }
  }
  out->push_back('"');
}

}  // namespace

void Json::DumpTo(std::string* out, int indent, int level) const {
  auto newline = [&](int lvl) {
    if (indent < 0) return;
    out->push_back('\n');
    out->append(static_cast<std::size_t>(indent * lvl), ' ');
  };
  if (is_null()) {
    *out += "null";
  } else if (is_bool()) {
    *out += std::get<bool>(value_) ? "true" : "false";
  } else if (is_number()) {
    const double v = std::get<double>(value_);
    if (!std::isfinite(v)) {
      *out += "null";  // JSON has no NaN/Inf
    } else if (v == std::floor(v) && std::fabs(v) < 1e15) {
      char buf[32];
      std::snprintf(buf, sizeof(buf), "%.0f", v);
      *out += buf;
    } else {
      char buf[32];
      std::snprintf(buf, sizeof(buf), "%.10g", v);
      *out += buf;
    }
  } else if (is_string()) {
    EscapeTo(std::get<std::string>(value_), out);
  } else if (is_array()) {
    const auto& a = std::get<Array>(value_);
    out->push_back('[');
    for (std::size_t i = 0; i < a.size(); ++i) {
      if (i) out->push_back(',');
      newline(level + 1);
      a[i].DumpTo(out, indent, level + 1);
    }
    if (!a.empty()) newline(level);
    out->push_back(']');
  } else {
    const auto& o = std::get<Object>(value_);
    out->push_back('{');
    bool first = true;
    for (const auto& [k, v] : o) {
      if (!first) out->push_back(',');
      first = false;
      newline(level + 1);
      EscapeTo(k, out);
      *out += indent < 0 ? ":" : ": ";
      v.DumpTo(out, indent, level + 1);
    }
    if (!o.empty()) newline(level);
    out->push_back('}');
  }
}

std::string Json::Dump(int indent) const {
  std::string out;
  DumpTo(&out, indent, 0);
  return out;
}

namespace {

class Parser {
 public:
  explicit Parser(std::string_view text) : text_(text) {}

  StatusOr<Json> ParseDocument() {
    auto value = ParseValue(0);
    if (!value.ok()) return value;
    SkipSpace();
    if (pos_ != text_.size()) return Error("trailing characters");
    return value;
  }

 private:
  Status Error(const std::string& what) const {
    return Corrupt("JSON: " + what + " at offset " + std::to_string(pos_));
  }
  void SkipSpace() {
    while (pos_ < text_.size() && (text_[pos_] == ' ' || text_[pos_] == '\n' ||
                                   text_[pos_] == '\t' || text_[pos_] == '\r')) {
      ++pos_;
    }
  }
  bool Consume(std::string_view word) {
    if (text_.substr(pos_, word.size()) != word) return false;
    pos_ += word.size();
    return true;
  }

  StatusOr<Json> ParseValue(int depth) {
    if (depth > 64) return Error("nesting too deep");
    SkipSpace();
    if (pos_ >= text_.size()) return Error("unexpected end");
    const char c = text_[pos_];
    if (c == '{') return ParseObject(depth);
    if (c == '[') return ParseArray(depth);
    if (c == '"') {
      auto s = ParseString();
      if (!s.ok()) return s.status();
      return Json(std::move(s).value());
    }
    if (Consume("true")) return Json(true);
    if (Consume("false")) return Json(false);
    if (Consume("null")) return Json();
    return ParseNumber();
  }

  StatusOr<Json> ParseNumber() {
    const std::size_t start = pos_;
    while (pos_ < text_.size() &&
           (std::isdigit(static_cast<unsigned char>(text_[pos_])) || text_[pos_] == '-' ||
            text_[pos_] == '+' || text_[pos_] == '.' || text_[pos_] == 'e' || text_[pos_] == 'E')) {
      ++pos_;
    }
    if (start == pos_) return Error("unexpected character");
    const std::string token(text_.substr(start, pos_ - start));
    char* end = nullptr;
    const double v = std::strtod(token.c_str(), &end);
    if (end != token.c_str() + token.size()) return Error("bad number");
    return Json(v);
  }

  StatusOr<std::string> ParseString() {
    ++pos_;  // opening quote
    std::string out;
    while (pos_ < text_.size()) {
      const char c = text_[pos_++];
      if (c == '"') return out;
      if (c != '\\') {
        out.push_back(c);
        continue;
      }
      if (pos_ >= text_.size()) break;
      const char e = text_[pos_++];
      switch (e) {
        case '"':
          out.push_back('"');
          break;
        case '\\':
          out.push_back('\\');
          break;
        case '/':
          out.push_back('/');
          break;
        case 'b':
          out.push_back('\b');
          break;
        case 'f':
          out.push_back('\f');
          break;
        case 'n':
          out.push_back('\n');
          break;
        case 'r':
          out.push_back('\r');
          break;
        case 't':
          out.push_back('\t');
          break;
        case 'u': {
          if (pos_ + 4 > text_.size()) return Error("bad escape");
          const unsigned code =
              std::strtoul(std::string(text_.substr(pos_, 4)).c_str(), nullptr, 16);
          pos_ += 4;
          // Basic multilingual plane only, as UTF-8.
          if (code < 0x80) {
            out.push_back(static_cast<char>(code));
          } else if (code < 0x800) {
            out.push_back(static_cast<char>(0xC0 | (code >> 6)));
            out.push_back(static_cast<char>(0x80 | (code & 0x3F)));
          } else {
            out.push_back(static_cast<char>(0xE0 | (code >> 12)));
            out.push_back(static_cast<char>(0x80 | ((code >> 6) & 0x3F)));
            out.push_back(static_cast<char>(0x80 | (code & 0x3F)));
          }
          break;
        }
        default:
          return Error("bad escape");
      }
    }
    return Error("unterminated string");
  }

  StatusOr<Json> ParseArray(int depth) {
    ++pos_;
    Json::Array a;
    SkipSpace();
    if (pos_ < text_.size() && text_[pos_] == ']') {
      ++pos_;
      return Json(std::move(a));
    }
    while (true) {
      auto v = ParseValue(depth + 1);
      if (!v.ok()) return v;
      a.push_back(std::move(v).value());
      SkipSpace();
      if (pos_ < text_.size() && text_[pos_] == ',') {
        ++pos_;
        continue;
      }
      if (pos_ < text_.size() && text_[pos_] == ']') {
        ++pos_;
        return Json(std::move(a));
      }
      return Error("expected , or ]");
    }
  }

  StatusOr<Json> ParseObject(int depth) {
    ++pos_;
    Json::Object o;
    SkipSpace();
    if (pos_ < text_.size() && text_[pos_] == '}') {
      ++pos_;
      return Json(std::move(o));
    }
    while (true) {
      SkipSpace();
      if (pos_ >= text_.size() || text_[pos_] != '"') return Error("expected a key");
      auto key = ParseString();
      if (!key.ok()) return key.status();
      SkipSpace();
      if (pos_ >= text_.size() || text_[pos_] != ':') return Error("expected :");
      ++pos_;
      auto v = ParseValue(depth + 1);
      if (!v.ok()) return v;
      o[std::move(key).value()] = std::move(v).value();
      SkipSpace();
      if (pos_ < text_.size() && text_[pos_] == ',') {
        ++pos_;
        continue;
      }
      if (pos_ < text_.size() && text_[pos_] == '}') {
        ++pos_;
        return Json(std::move(o));
      }
      return Error("expected , or }");
    }
  }

  std::string_view text_;
  std::size_t pos_ = 0;
};

}  // namespace

StatusOr<Json> Json::Parse(std::string_view text) { return Parser(text).ParseDocument(); }

Status WriteJsonFile(const Json& json, const std::string& path) {
  return WriteFileAtomic(path, json.Dump(2) + "\n");
}

StatusOr<Json> ReadJsonFile(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, 1ull << 28));
  auto parsed = Json::Parse(text);
  if (!parsed.ok()) return parsed.status().WithContext(path);
  return parsed;
}

}  // namespace ccmd
