#include "libccmd/net/refusal_log.h"

#include <cstdio>

#include "libccmd/util/logging.h"

namespace ccmd {

Status RefusalLogOptions::Validate() const {
  if (!(interval_s > 0)) return InvalidArgument("refusal log interval must be positive");
  if (max_sources == 0) return InvalidArgument("refusal log needs room for one source");
  return Status::Ok();
}

void RefusalLogOptions::Describe(OptionsWriter* out) const {
  out->Add("interval_s", interval_s);
  out->Add("max_sources", max_sources);
}
namespace {

constexpr const char* kOtherSources = "other sources";

}  // namespace

RefusalLog::RefusalLog(RefusalLogOptions options) : options_(std::move(options)) {}

void RefusalLog::Write(const std::string& line) {
  ++lines_;
  if (options_.sink) {
    options_.sink(line);
  } else {
    CCMD_LOG(WARNING) << line;
  }
}

void RefusalLog::Note(const std::string& source, const std::string& peer, const std::string& reason,
                      const std::string& text, double now) {
  Flush(now);
  std::string key = source;
  const std::size_t tracked = sources_.size() - sources_.count(kOtherSources);
  if (!sources_.count(key) && tracked >= options_.max_sources) key = kOtherSources;
  auto [it, added] = sources_.try_emplace(key);
  if (added) {
    it->second.interval_start = now;
    if (key != kOtherSources) {
      Write("refused connection from " + peer + ": " + text);
      return;
    }
  }
  ++it->second.suppressed;
  ++it->second.reasons[reason];
}

void RefusalLog::Summarise(const std::string& source, const Source& s, double now) {
  if (s.suppressed == 0) return;
  std::string reasons;
  for (const auto& [reason, n] : s.reasons) {
    reasons += (reasons.empty() ? "" : ", ") + std::to_string(n) + " " + reason;
  }
  char seconds[32];
  std::snprintf(seconds, sizeof(seconds), "%.1f", now - s.interval_start);
  Write(source + ": " + std::to_string(s.suppressed) + " more connection(s) refused in the last " +
        seconds + " s (" + reasons + ")");
}

void RefusalLog::Flush(double now, bool all) {
  for (auto it = sources_.begin(); it != sources_.end();) {
    if (all || now - it->second.interval_start >= options_.interval_s) {
      Summarise(it->first, it->second, now);
      it = sources_.erase(it);
    } else {
      ++it;
    }
  }
}

}  // namespace ccmd
