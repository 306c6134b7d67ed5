#pragma once

// A headless Chromium (Debian's `chromium`, installed by scripts/setup.sh) driven through the
// DevTools protocol over a pipe (--remote-debugging-pipe: JSON messages separated by NUL
// bytes on file descriptors 3 and 4), for the map view's browser test and benchmark. No
// network port, no driver program. WebGL runs on Chromium's software renderer.
//
// Everything waits on the browser's answers with a deadline; nothing sleeps.

#include <sys/types.h>

#include <memory>
#include <string>
#include <vector>

#include "libccmd/util/json.h"
#include "libccmd/util/status.h"

namespace ccmd::testing {

struct BrowserOptions {
  std::string executable = "chromium";
  int width = 1280, height = 800;
  double timeout_s = 60;  // per command unless told otherwise
  std::string log_path;   // Chromium's stderr ("" : discarded)
};

class HeadlessBrowser {
 public:
  // NotFound when Chromium is not installed (scripts/setup.sh installs it).
  static StatusOr<std::unique_ptr<HeadlessBrowser>> Launch(const BrowserOptions& options = {});
  ~HeadlessBrowser();  // closes the browser, waits for it, removes its profile folder
  HeadlessBrowser(const HeadlessBrowser&) = delete;
  HeadlessBrowser& operator=(const HeadlessBrowser&) = delete;

  // A new page at `url`; returns once its load event fired.
  Status Open(const std::string& url);
  // Evaluates JavaScript in the page; promises are awaited; the result comes back as JSON.
  // An exception in the page is an error with its description.
  StatusOr<Json> Evaluate(const std::string& expression, double timeout_s = -1);
  // The page as a PNG file's bytes.
  StatusOr<std::string> Screenshot();
  // Console messages and uncaught exceptions of the page so far (for failure messages).
  std::string PageLog() const { return page_log_; }

 private:
  HeadlessBrowser() = default;
  // Sends a command and waits for its answer; events that arrive meanwhile are kept.
  StatusOr<Json> Call(const std::string& method, Json params, double timeout_s = -1,
                      bool page = true);
  // Reads one message (waiting at most until `deadline`, MonotonicSeconds()).
  StatusOr<Json> Read(double deadline);
  void NoteEvent(const Json& message);

  BrowserOptions options_;
  pid_t pid_ = -1;
  int to_browser_ = -1, from_browser_ = -1;
  std::string profile_dir_, buffer_, session_, page_log_;
  std::vector<Json> events_;
  int next_id_ = 0;
};

// Standard base64 (screenshots).
StatusOr<std::string> DecodeBase64(const std::string& text);

}  // namespace ccmd::testing
