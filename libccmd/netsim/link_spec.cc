#include "libccmd/netsim/link_spec.h"

#include <cctype>
#include <cmath>
#include <cstdio>
#include <set>
#include <utility>
#include <vector>

#include "libccmd/util/string_util.h"

namespace ccmd {
namespace {

// Splits "2.4mbit" into 2.4 and "mbit".
std::pair<std::string, std::string> NumberAndUnit(const std::string& text) {
  std::size_t i = 0;
  while (i < text.size() &&
         (std::isdigit(static_cast<unsigned char>(text[i])) || text[i] == '.' || text[i] == 'e' ||
          text[i] == 'E' || text[i] == '-' || text[i] == '+')) {
    // An 'e' followed by a letter other than a digit or sign starts a unit, not an exponent.
    if ((text[i] == 'e' || text[i] == 'E') &&
        (i + 1 >= text.size() || !(std::isdigit(static_cast<unsigned char>(text[i + 1])) ||
                                   text[i + 1] == '-' || text[i + 1] == '+'))) {
      break;
    }
    ++i;
  }
  return {text.substr(0, i), text.substr(i)};
}

std::string Format(double v) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.9g", v);
  return text;
}

}  // namespace

StatusOr<double> ParseRateBytesPerSecond(const std::string& text) {
  const auto [number, unit] = NumberAndUnit(text);
  auto value = ParseDouble(number);
  if (!value.ok())
    return InvalidArgument("rate '" + text + "': expected a number with a unit, e.g. 2.4mbit");
  static const std::vector<std::pair<std::string, double>> kUnits = {
      {"bit", 1.0 / 8}, {"kbit", 1e3 / 8}, {"mbit", 1e6 / 8}, {"gbit", 1e9 / 8},
      {"bps", 1.0},     {"kbps", 1e3},     {"mbps", 1e6},     {"gbps", 1e9}};
  for (const auto& [name, factor] : kUnits) {
    if (unit == name) {
      if (!(*value > 0) || !std::isfinite(*value))
        return InvalidArgument("rate '" + text + "' must be positive");
      return *value * factor;
    }
  }
  return InvalidArgument(
      "rate '" + text +
      "': unknown unit (bit, kbit, mbit, gbit for bits per second; bps, kbps, mbps, gbps for "
      "bytes per second)");
}

StatusOr<double> ParseDurationSeconds(const std::string& text) {
  const auto [number, unit] = NumberAndUnit(text);
  auto value = ParseDouble(number);
  if (!value.ok())
    return InvalidArgument("duration '" + text + "': expected a number with a unit, e.g. 50ms");
  double factor = 0;
  if (unit == "us") factor = 1e-6;
  if (unit == "ms") factor = 1e-3;
  if (unit == "s" || unit.empty()) factor = 1;
  if (factor == 0) return InvalidArgument("duration '" + text + "': unknown unit (us, ms or s)");
  if (!(*value >= 0) || !std::isfinite(*value))
    return InvalidArgument("duration '" + text + "' must be >= 0");
  return *value * factor;
}

Status LinkSpec::Validate() const {
  if (!(rate_bytes_per_s >= 0) || !std::isfinite(rate_bytes_per_s))
    return InvalidArgument("link rate must be >= 0");
  if (rate_bytes_per_s > 0 && rate_bytes_per_s < 1000) {
    return InvalidArgument("link rate below 8kbit: too slow for a TCP session to work");
  }
  if (!(delay_s >= 0 && delay_s <= 10)) return InvalidArgument("link delay must be in [0, 10] s");
  if (!(jitter_s >= 0 && jitter_s <= delay_s)) {
    return InvalidArgument(
        "link jitter must be in [0, delay] (a packet cannot arrive before it left)");
  }
  if (!(loss >= 0 && loss < 1)) return InvalidArgument("link loss must be in [0, 1)");
  if (!(queue_s > 0 && queue_s <= 10)) return InvalidArgument("link queue must be in (0, 10] s");
  return Status::Ok();
}

std::string LinkSpec::ToString() const {
  std::string text;
  auto add = [&](const std::string& part) { text += (text.empty() ? "" : ",") + part; };
  if (rate_bytes_per_s > 0) add("rate=" + Format(rate_bytes_per_s) + "bps");
  add("delay=" + Format(delay_s) + "s");
  add("jitter=" + Format(jitter_s) + "s");
  add("loss=" + Format(loss));
  add("queue=" + Format(queue_s) + "s");
  add("seed=" + std::to_string(seed));
  return text;
}

StatusOr<LinkSpec> ParseLinkSpec(const std::string& text) {
  LinkSpec spec;
  std::set<std::string> seen;
  if (Trim(text).empty())
    return InvalidArgument("empty link spec (e.g. rate=2.4mbit,delay=50ms,loss=0.02)");
  for (const std::string& raw : Split(text, ',')) {
    const std::string part(Trim(raw));
    const std::size_t eq = part.find('=');
    if (eq == std::string::npos)
      return InvalidArgument("link spec part '" + part + "' is not key=value");
    const std::string key(Trim(part.substr(0, eq))), value(Trim(part.substr(eq + 1)));
    if (!seen.insert(key).second) return InvalidArgument("link spec sets '" + key + "' twice");
    if (key == "rate") {
      CCMD_ASSIGN_OR_RETURN(spec.rate_bytes_per_s, ParseRateBytesPerSecond(value));
    } else if (key == "delay") {
      CCMD_ASSIGN_OR_RETURN(spec.delay_s, ParseDurationSeconds(value));
    } else if (key == "jitter") {
      CCMD_ASSIGN_OR_RETURN(spec.jitter_s, ParseDurationSeconds(value));
    } else if (key == "queue") {
      CCMD_ASSIGN_OR_RETURN(spec.queue_s, ParseDurationSeconds(value));
    } else if (key == "loss") {
      const bool percent = !value.empty() && value.back() == '%';
      auto v = ParseDouble(percent ? value.substr(0, value.size() - 1) : value);
      if (!v.ok())
        return InvalidArgument("link loss '" + value +
                               "': expected a fraction (0.02) or a percentage (2%)");
      spec.loss = percent ? *v / 100 : *v;
    } else if (key == "seed") {
      auto v = ParseInt(value);
      if (!v.ok() || *v < 0)
        return InvalidArgument("link seed '" + value + "' must be a non-negative integer");
      spec.seed = static_cast<std::uint64_t>(*v);
    } else {
      return InvalidArgument("unknown link spec key '" + key +
                             "' (rate, delay, jitter, loss, queue, seed)");
    }
  }
  CCMD_RETURN_IF_ERROR(spec.Validate());
  return spec;
}

}  // namespace ccmd
