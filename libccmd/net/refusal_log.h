#pragma once

// Rate-limited logging of refused connections (bad bytes, failed or abandoned handshakes,
// a full server), so that a storm of them cannot flood the log: per source address, the
// first refusal of each interval is logged in full; the rest are counted and summarised in
// one line per source when its interval ends:
//
//   refused connection from 10.0.0.7:51334: authentication failed: ...
//   10.0.0.7: 1579 more connections refused in the last 10.0 s (1200 time-out, 379
//   protocol error)
//
// Memory: one entry per source seen in the current interval, at most max_sources; refusals
// from further sources are summarised together. Not thread-safe (the server's I/O thread).

#include <cstdint>
#include <functional>
#include <map>
#include <string>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct RefusalLogOptions {
  double interval_s = 10.0;
  std::size_t max_sources = 256;
  // Where lines go (default: CCMD_LOG(WARNING)); tests collect them.
  std::function<void(const std::string&)> sink;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class RefusalLog {
 public:
  explicit RefusalLog(RefusalLogOptions options = {});
  // A refused connection from `source` (an address without the port), `peer` (with it), for
  // `reason` (a short kind, e.g. "time-out"), described by `text`.
  void Note(const std::string& source, const std::string& peer, const std::string& reason,
            const std::string& text, double now);
  // Writes the summaries of intervals that have ended by `now` (all of them if `all`).
  void Flush(double now, bool all = false);
  std::uint64_t lines() const { return lines_; }

 private:
  struct Source {
    double interval_start = 0;
    std::uint64_t suppressed = 0;
    std::map<std::string, std::uint64_t> reasons;
  };
  void Write(const std::string& line);
  void Summarise(const std::string& source, const Source& s, double now);

  RefusalLogOptions options_;
  std::map<std::string, Source> sources_;
  std::uint64_t lines_ = 0;
};

}  // namespace ccmd
